// Undo / redo of edits (Ctrl+Z, Ctrl+Shift+Z or Ctrl+Y, the buttons). Each entry holds
// the edit messages that redo it and those that undo it, computed from the frame's
// state before the edit (its 2D edits, fixed and invisible flags), so undoing replays
// what the server had. A 3D edit (Edit 3D) is undone exactly back to a point without
// corrections; over an earlier 3D edit of the same point, undo restores the 2D state
// and that earlier 3D edit is lost (the page does not see 3D edits' coordinates).

export class EditHistory {
  constructor(limit = 200) {
    this.done = [];
    this.undone = [];
    this.limit = limit;
  }

  record(entry) {
    this.done.push(entry);
    if (this.done.length > this.limit) this.done.shift();
    this.undone = [];
  }

  takeUndo() {
    const entry = this.done.pop();
    if (entry) this.undone.push(entry);
    return entry;
  }

  takeRedo() {
    const entry = this.undone.pop();
    if (entry) this.done.push(entry);
    return entry;
  }

  get canUndo() { return this.done.length > 0; }
  get canRedo() { return this.undone.length > 0; }
}

// The messages that put the given points of one frame back as `data` (a /api/points
// reply) has them: clear each point everywhere, then replay its 2D edits and flags.
export function restoreMessages(data, points) {
  const messages = [];
  for (const point of points) {
    messages.push({ op: "reset_point", frame: data.frame, point });
    data.views.forEach((v) => {
      if (v.invisible[point]) {
        messages.push({ op: "invisible", frame: data.frame, point, view: v.name });
      } else if (v.edited[point] && v.points2d[point]) {
        messages.push({
          op: "move", frame: data.frame, point, view: v.name, xy: v.points2d[point],
          fixed: Boolean(v.fixed && v.fixed[point]),
        });
      }
    });
  }
  return messages;
}

// Which points an edit message can change.
export function touchedPoints(message, nPoints) {
  if (message.op === "reset_view" || message.op === "reset_frame") {
    return [...Array(nPoints).keys()];
  }
  return [message.point];
}
