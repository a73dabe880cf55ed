// The suspect list: items (a point's consecutive suspect frames), best first by
// default, sortable; the rows of the current frame are marked and scrolled into view.

const KEYS = {
  frame: (it) => it.first_frame,
  point_name: (it) => it.point_name,
  score: (it) => it.score,
  reasons: (it) => it.reasons.join(),
};

function order(sort) {
  const get = KEYS[sort.key] || KEYS.score;
  return (a, b) => {
    const x = get(a), y = get(b);
    const c = x < y ? -1 : x > y ? 1 : 0;
    return (sort.asc ? c : -c) || a.rank - b.rank;  // ties: the better item first
  };
}

export function sortedItems(items, sort) {
  return [...items].sort(order(sort));
}

export const sameItem = (a, b) => a.point === b.point && a.frames.some((f) => b.frames.includes(f));

export function framesText(item) {
  return item.first_frame === item.last_frame ? String(item.first_frame)
    : `${item.first_frame}\u2013${item.last_frame}`;
}

export function renderItems(tbody, items, sort, frame, reviewed, onPick) {
  const rows = sortedItems(items, sort).map((item) => {
    const tr = document.createElement("tr");
    const done = item.frames.every((f) => reviewed.has(`${item.point}:${f}`));
    tr.className = done ? "reviewed" : "";
    tr.title = `frames ${item.frames.join(", ")}; at ${item.peak_frame}: ${item.detail}`;
    tr.dataset.rank = String(item.rank);
    tr.frames = item.frames;
    for (const text of [framesText(item), (done ? "\u2713 " : "") + item.point_name, item.score.toFixed(2), item.reasons.join(", ")]) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.appendChild(td);
    }
    tr.addEventListener("click", () => onPick(item));
    return tr;
  });
  tbody.replaceChildren(...rows);
  markCurrent(tbody, frame);
}

export function markCurrent(tbody, frame) {
  // the rows of the frame's items marked, the first scrolled into view once per frame
  // (a frame step touches only these classes: rebuilding a long list took most of a step)
  let first = null;
  for (const tr of tbody.rows) {
    const covers = tr.frames.includes(frame);
    tr.classList.toggle("current", covers);
    if (covers) first ||= tr;
  }
  if (first && frame !== shownFrame) keepVisible(first);
  shownFrame = frame;
}

let shownFrame = null;  // the list scrolls to the current frame's items once per frame

function keepVisible(row) {
  // scroll the list's own box only (scrollIntoView would also scroll the page under a drag)
  const box = row.closest("#side") || row.parentElement;
  const r = row.getBoundingClientRect(), b = box.getBoundingClientRect();
  const header = row.closest("table")?.querySelector("thead")?.getBoundingClientRect().height || 0;
  if (r.top < b.top + header) box.scrollTop -= b.top + header - r.top;
  else if (r.bottom > b.bottom) box.scrollTop += r.bottom - b.bottom;
}

export function neighbourItem(items, sort, frame, point, direction, last = null) {
  // the item after / before the one at (frame, point) in the list's order; off every item,
  // the one after / before the item last gone to (`last`, where it sorts if it left the list)
  const list = sortedItems(items, sort), n = list.length;
  if (!n) return null;
  const here = list.findIndex((it) => it.point === point && it.frames.includes(frame));
  if (here >= 0) return list[(here + direction + n) % n];
  if (sort.key === "frame" && sort.asc) {
    // in time order: the next (previous) item in time, else the list's ends
    if (direction > 0) return list.find((it) => it.first_frame > frame) ?? list[0];
    return [...list].reverse().find((it) => it.last_frame < frame) ?? list[n - 1];
  }
  if (!last) return direction > 0 ? list[0] : list[n - 1];
  const at = list.findIndex((it) => sameItem(it, last));
  if (at >= 0) return list[(at + direction + n) % n];
  const after = list.findIndex((it) => order(sort)(it, last) > 0);
  const next = after < 0 ? n : after;
  return list[((direction > 0 ? next : next - 1) + n) % n];
}

export function itemPlan(frames, edited) {
  // the positions for an item's frames from its edited ones: between two edited frames
  // interpolated linearly, before the first / after the last the nearest edited one's
  const keys = frames.filter((f) => edited[f]);
  const plan = {};
  if (!keys.length) return plan;
  for (const f of frames) {
    if (edited[f]) continue;
    const after = keys.find((k) => k > f), before = [...keys].reverse().find((k) => k < f);
    if (before !== undefined && after !== undefined) {
      const w = (f - before) / (after - before);
      plan[f] = edited[before].map((c, i) => c + w * (edited[after][i] - c));
    } else {
      plan[f] = [...edited[before !== undefined ? before : after]];
    }
  }
  return plan;
}
