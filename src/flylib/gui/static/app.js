// flylib gui: the page. Plain ES modules, one <canvas> per camera view.
import { alertText, clearAlert, showAlert } from "./alerts.js";
import { apiUrl, EditChannel, getJSON, postJSON } from "./api.js";
import { drawTimeline, drawView, fitTransform, toCanvas, toImage } from "./draw.js";
import { EditHistory, restoreMessages, touchedPoints } from "./history.js";
import { applyLayout } from "./layout.js";
import { buildLegend, drawFixedMark, drawPointLabel } from "./legend.js";
import { FramesAhead } from "./ahead.js";
import { framesText, itemPlan, markCurrent, neighbourItem, renderItems, sameItem } from "./suspects.js";
import { View3D } from "./view3d.js";

const $ = (sel) => document.querySelector(sel);
const state = {
  meta: null, frame: 0, data: null, images: {}, views: [], zoom: {},
  focus: 0, layout: "grid", editMode: false, mode: "view", selected: null,  // {view, point}
  suspects: [], items: [], frameScore: [], suspectFrames: [], sort: { key: "score", asc: false },
  drawn: {}, lastServerMs: null, requestId: 0, hover: null, history: new EditHistory(), view3d: null,
  revision: 0, offline: false,
  // the display, kept per recording in this browser (localStorage)
  display: { overlay: true, labels: false, limb: null, brightness: 100, contrast: 100, gamma: 1 },
  peek: false, playing: null,
};
const channel = new EditChannel({ onLost: serverLost, onChanged: changedElsewhere });

function status(text) { $("#status").textContent = text; }

// Keys and buttons act in the order pressed, each once the one before finished its round
// trips: typed ahead, a key acts on the frame, item and point the keys before it left.
const actions = { pending: [], running: false, sending: 0 };

function act(run, step = 0) {
  const last = actions.pending[actions.pending.length - 1];
  if (step && last && last.step) last.step += step;  // a held arrow key: one jump
  else actions.pending.push({ run, step });
  if (!actions.running) drain();
  showBusy();
}

async function drain() {
  actions.running = true;
  while (actions.pending.length) {
    const { run, step } = actions.pending.shift();
    showBusy();
    try { await (step ? goto(state.frame + step) : run()); } catch (err) { status(err.message); console.error(err); }
  }
  actions.running = false;
  showBusy();
}

function showBusy() {
  const waiting = actions.pending.length;
  $("#busy").hidden = !actions.running && !actions.sending;
  $("#busy").textContent = waiting ? `working\u2026 (${waiting} queued)` : "working\u2026";
}

async function start() {
  state.meta = await getJSON("/api/meta");
  const meta = state.meta;
  state.revision = meta.revision;
  $("#recording").textContent = meta.results;
  if (meta.notice) showAlert(meta.notice, "info");
  if (meta.footage_missing) {
    $("#footage-banner").textContent = meta.footage_missing;
    $("#footage-banner").hidden = false;
  }
  const slider = $("#slider");
  slider.max = meta.frames - 1;
  slider.addEventListener("input", () => goto(Number(slider.value)));
  const container = $("#views");
  meta.views.forEach((view, i) => {
    const div = document.createElement("div");
    div.className = "view";
    const canvas = document.createElement("canvas");
    const label = document.createElement("span");
    label.className = "label";
    label.textContent = `${i + 1} ${view.name}`;
    div.append(canvas, label);
    container.appendChild(div);
    canvas.dataset.view = view.name;
    state.views.push({ ...view, index: i, div, canvas, transform: null });
    state.zoom[view.name] = { scale: 1, x: 0, y: 0 };
    attachMouse(state.views[i]);
  });
  const tile3d = document.createElement("div");
  tile3d.className = "view view3d";
  const canvas3d = document.createElement("canvas");
  const label3d = document.createElement("span");
  label3d.className = "label clickable";
  label3d.textContent = "3D (fly scale)";
  label3d.title = "click: fly scale / rig scale";
  label3d.addEventListener("click", () => { label3d.textContent = `3D (${state.view3d.toggleScale()} scale)`; });
  tile3d.append(canvas3d, label3d);
  container.appendChild(tile3d);
  state.tile3d = tile3d;
  state.view3d = new View3D(canvas3d, meta, (point) => {
    state.selected = { view: (state.selected && state.selected.view) || state.views[0].name, point };
    redrawAll();
  });
  buildLegend($("#legend"), meta);
  loadDisplay();
  buildDisplayControls();
  new ResizeObserver(() => { relayout(); redrawAll(); }).observe(container);
  wireControls();
  let panel = null;
  try { panel = localStorage.getItem("flylib.panel"); } catch { /* private mode */ }
  setPanel(panel ? panel === "open" : window.innerWidth >= 1500);
  await loadSuspects();
  await goto(initialFrame(new URLSearchParams(location.search).get("frame")));
  watchResults();
}

function watchResults() {
  // a re-run rewrote results.h5: this page shows the old result until reloaded
  const check = setInterval(async () => {
    if (state.offline) return;
    let meta;
    try { meta = await getJSON("/api/meta"); } catch { return; }
    if (!meta.results_changed) return;
    clearInterval(check);
    const dirty = state.data && state.data.dirty;
    $("#results-banner span").textContent = `${meta.results} was rewritten on disk (the workflow ` +
      "ran again?): the views still show the result this page opened. Reload reads the new one" +
      (dirty ? "; the unsaved edits are journaled and replayed onto it." : ".");
    $("#results-banner").hidden = false;
  }, RESULTS_CHECK_MS);
}

const RESULTS_CHECK_MS = 3000;

async function reloadResults() {
  try {
    await postJSON("/api/reload", {});
  } catch (err) {
    return showAlert(`not reloaded: ${err.detail || err.message}`);
  }
  location.reload();
}

function initialFrame(asked) {
  // ?frame=N: clamped to the recording; anything but a whole number is ignored, said once
  if (asked === null || asked === "") return 0;
  const last = state.meta.frames - 1;
  if (!/^-?\d+$/.test(asked.trim())) {
    status(`?frame=${asked} is not a frame number; showing frame 0 (frames 0..${last})`);
    return 0;
  }
  const frame = Number(asked);
  if (frame < 0 || frame > last) status(`?frame=${asked} is outside 0..${last}; showing frame ${Math.max(0, Math.min(last, frame))}`);
  return Math.max(0, Math.min(last, frame));
}

function relayout() {
  const tiles = [...state.views.map((v) => v.div), state.tile3d];
  const first = state.meta.views[0];
  applyLayout($("#views"), tiles, state.layout, state.focus, first.width / first.height);
}

// -- frames --------------------------------------------------------------------------

async function goto(frame) {
  // the frame's images and points drawn together, once all are here (fetched ahead: at once)
  const meta = state.meta;
  frame = Math.max(0, Math.min(meta.frames - 1, Math.round(frame)));
  state.frame = frame;
  const id = ++state.requestId;
  $("#slider").value = frame;
  $("#frame-label").textContent = `/ ${meta.frames - 1}`;
  if (document.activeElement !== $("#frame-input")) $("#frame-input").value = String(frame);
  state.ahead ||= new FramesAhead(state.views.map((v) => v.name));
  const entry = state.ahead.get(frame, Boolean(state.playing));
  const bitmaps = await Promise.all(state.views.map((view) => entry.images[view.name]));
  let data = await entry.points;
  if (data.revision !== state.revision) data = await getJSON(`/api/points/${frame}`);  // edited since
  if (id !== state.requestId) return;
  followPoint(state.data, data);
  state.views.forEach((view, i) => { if (bitmaps[i]) state.images[view.name] = { bitmap: bitmaps[i], frame }; });
  state.data = data;
  state.revision = data.revision;
  redrawAll();
  markCurrent($("#suspects tbody"), frame);
  state.ahead.want(framesAhead(frame), Boolean(state.playing));
}

function framesAhead(frame) {
  // the next frames (half a second's while playing), the previous one, the next / previous item
  const n = state.playing ? Math.max(4, Math.ceil(state.playing.fps / 2)) : 4;
  const first = state.playing ? Math.max(frame, state.playing.due() - 1) : frame;
  const point = state.selected ? state.selected.point : null;
  const items = state.items.length ? [1, -1].map((d) => neighbourItem(state.items, state.sort, frame, point, d).peak_frame) : [];
  return [...Array.from({ length: n }, (_, i) => first + 1 + i), frame - 1, ...items]
    .filter((f) => f >= 0 && f < state.meta.frames);
}

const pointAt = (data, view, point) => data && (data.views[view.index].points2d[point] || data.views[view.index].reprojected[point]);

function followPoint(before, after) {
  // focused on a point, each zoomed view pans with it from frame to frame (it stays where it was)
  if (state.layout !== "focus" || !state.selected) return;
  for (const view of state.views) {
    const a = pointAt(before, view, state.selected.point), b = pointAt(after, view, state.selected.point);
    const z = state.zoom[view.name];
    if (!a || !b || z.scale <= 1 || !view.transform) continue;
    z.x -= (b[0] - a[0]) * view.transform.scale;
    z.y -= (b[1] - a[1]) * view.transform.scale;
  }
}

function resize(view) {
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(view.canvas.clientWidth * dpr));
  const h = Math.max(1, Math.round(view.canvas.clientHeight * dpr));
  if (view.canvas.width !== w || view.canvas.height !== h) {
    // a zoomed view keeps showing the same part of the frame at its new size
    const z = state.zoom[view.name];
    if (view.canvas.width > 1 && view.canvas.height > 1) {
      z.x *= w / view.canvas.width;
      z.y *= h / view.canvas.height;
    }
    view.canvas.width = w;
    view.canvas.height = h;
  }
}

function draw(view) {
  resize(view);
  const image = state.images[view.name];
  const sel = state.selected && state.selected.view === view.name ? state.selected.point : null;
  const d = state.display;
  view.transform = drawView(view.canvas, image && image.bitmap, view, state.meta, state.data,
    { zoom: state.zoom[view.name], viewIndex: view.index, selected: sel, overlay: d.overlay,
      limb: d.limb, peek: state.peek, filter: footageFilter() });
  if (!state.peek) drawMarks(view, sel);
  if (state.data && state.data.frame === state.frame && image && image.frame === state.frame) {
    view.canvas.dataset.drawnFrame = String(state.frame);
  }
}

function drawMarks(view, selected) {
  // fixed points, and the names of the hovered and the selected point
  if (!state.data || !view.transform) return;
  const v = state.data.views[view.index];
  (v.fixed || []).forEach((isFixed, p) => {
    if (isFixed && v.points2d[p]) drawFixedMark(view.canvas, toCanvas(view.transform, v.points2d[p]));
  });
  const hover = state.hover && state.hover.view === view.name ? state.hover.point : null;
  const shown = (p) => state.display.limb === null || state.meta.point_limbs[p] === state.display.limb;
  // labels always on (l): every drawn point's name; else the hovered and the selected one;
  // a thumbnail names none (at ~100 px the name covers its view's label; the item line names it)
  const named = state.display.labels ? state.meta.points.map((_, p) => p).filter(shown) : [];
  const thumbnail = state.layout === "focus" && view.index !== state.focus;
  view.labelled = [];  // the names drawn (the browser test reads them)
  for (const p of new Set(thumbnail ? [] : [...named, selected, hover])) {
    if (p === null || p === undefined) continue;
    const xy = v.points2d[p] || v.reprojected[p];
    if (!xy) continue;
    view.labelled.push(p);
    drawPointLabel(view.canvas, toCanvas(view.transform, xy), state.meta.points[p], state.meta.point_colors[p]);
  }
}

// -- display: overlay, labels, one limb, brightness / contrast / gamma -----------------

function footageFilter() {
  const d = state.display;
  if (d.brightness === 100 && d.contrast === 100 && d.gamma === 1) return "none";
  return `brightness(${d.brightness}%) contrast(${d.contrast}%)` + (d.gamma !== 1 ? " url(#gamma)" : "");
}

function displayKey() { return `flylib.display:${state.meta.results}`; }

function loadDisplay() {
  try {
    const saved = JSON.parse(localStorage.getItem(displayKey()) || "null");
    if (saved && typeof saved === "object") {
      for (const key of Object.keys(state.display)) if (key in saved) state.display[key] = saved[key];
    }
  } catch { /* private mode or a damaged entry: the defaults */ }
  if (state.display.limb !== null && !(state.display.limb >= 0 && state.display.limb < state.meta.limbs.length)) state.display.limb = null;
}

function setDisplay(change) {
  Object.assign(state.display, change);
  try { localStorage.setItem(displayKey(), JSON.stringify(state.display)); } catch { /* private mode */ }
  showDisplay();
  redrawAll();
}

function showDisplay() {
  // the controls show the display's state
  const d = state.display;
  $("#overlay").classList.toggle("active", d.overlay);
  $("#labels").classList.toggle("active", d.labels);
  $("#limb").value = d.limb === null ? "" : String(d.limb);
  for (const key of ["brightness", "contrast", "gamma"]) {
    $(`#${key}`).value = String(d[key]);
    $(`#${key}-value`).textContent = key === "gamma" ? d.gamma.toFixed(2) : `${d[key]}%`;
  }
  // what hides points, said in the header too (the panel may be closed)
  const hiding = [!d.overlay && "overlay off (o)", d.limb !== null && `only ${state.meta.limbs[d.limb]} ([ ])`].filter(Boolean);
  $("#display-state").textContent = hiding.join(", ");
  $("#display-state").hidden = !hiding.length;
  // gamma: the SVG filter the footage is drawn through (CSS filters have none)
  for (const f of document.querySelectorAll("#gamma feFuncR, #gamma feFuncG, #gamma feFuncB")) {
    f.setAttribute("exponent", String(1 / d.gamma));
  }
}

function buildDisplayControls() {
  const select = $("#limb");
  const all = document.createElement("option");
  all.value = "";
  all.textContent = "all limbs";
  select.replaceChildren(all, ...state.meta.limbs.map((name, i) => {
    const option = document.createElement("option");
    option.value = String(i);
    option.textContent = name;
    return option;
  }));
  select.addEventListener("change", () => setDisplay({ limb: select.value === "" ? null : Number(select.value) }));
  $("#overlay").addEventListener("click", () => setDisplay({ overlay: !state.display.overlay }));
  $("#labels").addEventListener("click", () => setDisplay({ labels: !state.display.labels }));
  for (const key of ["brightness", "contrast", "gamma"]) {
    $(`#${key}`).addEventListener("input", () => setDisplay({ [key]: Number($(`#${key}`).value) }));
  }
  $("#display-reset").addEventListener("click", () => setDisplay({ brightness: 100, contrast: 100, gamma: 1 }));
  showDisplay();
}

function cycleLimb(direction) {
  // [ / ]: show one limb after another, then all
  const n = state.meta.limbs.length;
  const at = state.display.limb === null ? (direction > 0 ? -1 : n) : state.display.limb;
  const next = at + direction;
  setDisplay({ limb: next < 0 || next >= n ? null : next });
  status(state.display.limb === null ? "all limbs shown" : `only ${state.meta.limbs[state.display.limb]} shown ([ ] for another, all after the last)`);
}

// -- playback --------------------------------------------------------------------------

function togglePlay() {
  // space: play from here at the chosen frames per second, showing the latest frame fetched
  // of those due: frames not fetched in time are skipped (the rate holds), and the fetches
  // ahead start at the due frame (awaiting a late frame, frames between were fetched unseen);
  // frames at half size while playing (a quarter of the pixels), the one it stops at at full size
  if (state.playing) { state.playing = null; $("#play").textContent = "\u25B6"; return act(() => goto(state.frame)); }
  const playing = { fps: Number($("#fps").value) };  // kept within 1..120 as typed
  state.playing = playing;
  $("#play").textContent = "\u275A\u275A";
  const from = state.frame, started = performance.now(), last = state.meta.frames - 1;
  playing.due = () => Math.min(last, from + 1 + Math.floor(((performance.now() - started) * playing.fps) / 1000));
  (async () => {
    while (state.playing === playing) {
      if (state.frame >= last) { togglePlay(); return; }
      const due = Math.max(state.frame + 1, playing.due());
      const next = [...Array(due - state.frame).keys()].map((i) => due - i).find((f) => state.ahead.isReady(f));
      if (next === undefined) state.ahead.want(framesAhead(state.frame), true); else await goto(next);
      const wait = next === undefined ? 10 : started + ((next - from) * 1000) / playing.fps - performance.now();
      await new Promise((done) => setTimeout(done, Math.max(0, wait)));
    }
  })().catch((err) => { status(err.message); if (state.playing === playing) togglePlay(); });
}

async function stopServer() {
  // the page's Stop button: the server exits (unsaved edits stay journaled)
  const dirty = state.data && state.data.dirty;
  if (!confirm(dirty ? "Stop flylib gui? The unsaved edits stay in the journal and come back with the next `flylib gui`." : "Stop flylib gui?")) return;
  try {
    await postJSON("/api/stop", {});
  } catch (err) {
    status(`not stopped: ${err.detail || err.message}`);
  }
}

function redrawAll() {
  state.views.forEach(draw);
  if (state.view3d) state.view3d.update(state.data, state.selected ? state.selected.point : null);
  showSelection();
  showItemLine();
  $("#undo").disabled = !state.history.canUndo;
  $("#redo").disabled = !state.history.canRedo;
  drawTimeline($("#timeline"), state.frameScore, new Set(state.suspectFrames), state.frame);
  // the count on Save: what the next save adds (edits and review marks since the last one)
  const edits = state.data ? state.data.edits : 0, unsaved = state.data ? state.data.unsaved : 0;
  $("#save").classList.toggle("dirty", Boolean(state.data && state.data.dirty));
  $("#save").textContent = unsaved ? `Save (${unsaved})` : "Save";
  $("#save").title = `write corrections.h5 (s): ${unsaved} unsaved change(s); ${edits} point edit(s) in all`;
}

// -- suspects --------------------------------------------------------------------------

function showSelection() {
  const s = state.selected;
  const label = $("#selection");
  if (!s) { label.textContent = "no point selected"; return; }
  const view = state.views.find((v) => v.name === s.view);
  const v = state.data && view ? state.data.views[view.index] : null;
  const flags = v ? [v.edited[s.point] && "edited", v.fixed && v.fixed[s.point] && "fixed",
    v.invisible[s.point] && "invisible", v.used[s.point] === false && v.points2d[s.point] && "dropped"].filter(Boolean) : [];
  label.textContent = `${state.meta.points[s.point]} in ${view ? view.index + 1 : "?"} ${s.view}` +
    (flags.length ? ` (${flags.join(", ")})` : "");
}

function showItemLine() {
  // the item worked on, one line under the frames: rank, reason here, frames, error here
  const item = state.item, s = state.selected, line = $("#item-line");
  if (!item) { line.textContent = `${state.items.length} suspect items: n / u go to them`; line.title = ""; return; }
  const live = state.items.find((it) => sameItem(it, item));
  const here = state.suspects.find((r) => r.point === item.point && r.frame === state.frame);
  const view = s && s.point === item.point ? state.views.find((v) => v.name === s.view) : null;
  const error = view && state.data ? state.data.views[view.index].error[item.point] : null;
  line.textContent = [live ? `#${live.rank + 1} of ${state.items.length}` : "no longer suspect", item.point_name,
    `frames ${framesText(live || item)}`, !item.frames.includes(state.frame) ? `frame ${state.frame} is outside it`
      : here ? here.detail : "not suspect at this frame",
    view && `error here ${error === null ? "none (not used)" : `${error.toFixed(1)} px`} in ${view.name}`,
  ].filter(Boolean).join(" \u00b7 ");
  line.title = line.textContent;
}

async function loadSuspects() {
  const payload = await getJSON("/api/suspects");
  state.suspects = payload.suspects;
  state.items = payload.items || [];
  state.review = payload.review || { items: [], done: 0, total: 0 };
  $("#progress").textContent = `${state.review.done} / ${state.review.total} reviewed`;
  state.frameScore = payload.frame_score;
  state.suspectFrames = [...new Set(state.suspects.map((s) => s.frame))].sort((a, b) => a - b);
  $("#suspect-count").textContent =
    `(${state.items.length} items: ${state.suspects.length} points in ${state.suspectFrames.length} frames)`;
  const timeline = $("#timeline");
  timeline.width = timeline.clientWidth || 800;
  timeline.height = timeline.clientHeight || 36;
  renderSuspectTable();
}

function renderSuspectTable() {
  const done = new Set((state.review ? state.review.items : []).filter((it) => it.done)
    .flatMap((it) => it.frames.map((f) => `${it.point}:${f}`)));
  renderItems($("#suspects tbody"), state.items, state.sort, state.frame, done,
    (item) => act(() => jumpToSuspect(item)));
  document.querySelectorAll("#suspects th").forEach((th) => {
    th.classList.toggle("sorted", th.dataset.key === state.sort.key);
    th.classList.toggle("asc", th.dataset.key === state.sort.key && state.sort.asc);
  });
}

async function jumpToSuspect(item) {
  // the item (a point's consecutive suspect frames) stays the one worked on after its
  // frames are corrected and it leaves the list (a = apply to it; n / p go on from it)
  state.item = { ...item, frames: [...item.frames] };
  await goto(item.peak_frame);
  const view = bestViewFor(item.point);
  state.selected = { view: view.name, point: item.point };
  focusOn(view, item.point);
}

function bestViewFor(point) {
  // the view where the point is drawn with the largest reprojection error (else the first that sees it)
  let best = null, bestError = -1;
  state.data.views.forEach((v, i) => {
    if (!v.points2d[point]) return;
    const e = v.error[point] ?? 0;
    if (e > bestError) { best = state.views[i]; bestError = e; }
  });
  return best || state.views[0];
}

function stepSuspect(direction) {
  // n / p: the next / previous item in the list's order, at its worst frame
  if (!state.items.length) return status("no suspects");
  const point = state.selected ? state.selected.point : null;
  return jumpToSuspect(neighbourItem(state.items, state.sort, state.frame, point, direction, state.item));
}

// -- editing ---------------------------------------------------------------------------

async function submit(message) {
  // one edit to the server, against the revision this page shows; the reply, or null
  // when it was not applied (stale: another tab edited; refused: bad input; not stored:
  // journal unwritable or server gone), after which the page shows the server's state
  if (state.offline) { status("not stored: flylib gui is not running"); return null; }
  const reply = await channel.send({ frame: state.frame, revision: state.revision, ...message });
  if (reply.op !== "points") {
    if (reply.op === "not_stored") showAlert(`edit not stored: ${reply.error}`);
    else status(`edit ${reply.op === "stale" ? "not applied" : "refused"}: ${reply.error}`);
    if (reply.op === "stale") dropHistory();
    if (!state.offline) await refresh();
    return null;
  }
  state.revision = reply.revision;
  if (reply.frame === state.frame) state.data = reply;
  return reply;
}

async function sendEdit(message, drag = null) {
  // what puts the touched points back is taken from the frame before this edit (a drag:
  // before its first step); the history keeps it once the server applied the edit
  const frame = state.frame;
  const before = drag ? drag.before
    : restoreMessages(state.data, touchedPoints(message, state.meta.points.length));
  const reply = await submit(message);
  if (!reply) return null;
  const redo = [{ frame, ...message, durable: true }];
  if (drag && drag.recorded) state.history.done[state.history.done.length - 1].redo = redo;
  else state.history.record({ frame, undo: before, redo });
  if (drag) drag.recorded = true;
  state.lastServerMs = reply.server_ms;
  status(`${message.op}: re-solved in ${reply.server_ms} ms on the server`);
  if (message.durable !== false) sayConsequences([reply]);  // a drag: once, at its end
  redrawAll();
  return reply;
}

function sayConsequences(replies) {
  // at once, what edits made worse: another view's error raised, or the edited view left
  // out by the robust triangulation; the next edit or undo replaces the line
  const lines = replies.map((r) => r.consequence && consequenceText(r.consequence, r.frame)).filter(Boolean);
  $("#consequence").textContent = lines.length ? `${lines.join("; ")} \u2014 Ctrl+Z to undo` : "";
  $("#consequence").hidden = !lines.length;
}

function consequenceText(c, frame) {
  const said = c.rose.map((r) => r.after === null
    ? `view ${r.view} dropped by the robust triangulation (was ${r.before.toFixed(1)} px)`
    : `view ${r.view}'s error rose ${r.before.toFixed(1)} \u2192 ${r.after.toFixed(1)} px`);
  if (c.dropped !== null) said.unshift(`dropped by the robust triangulation (${c.dropped.toFixed(1)} px from its 3D)`);
  return said.length ? `${state.meta.points[c.point]} in ${c.view} at frame ${frame}: ${said.join(", ")}` : "";
}

async function replay(entry, which) {
  // undo / redo: the entry's messages through the same edit path as any edit (checked,
  // journaled, against the page's revision)
  if (!entry) return status(`nothing to ${which}`);
  if (entry.frame !== state.frame) await goto(entry.frame);
  for (const message of entry[which]) {
    if (!(await submit(message))) { status(`${which} stopped: ${$("#status").textContent}`); return; }
  }
  await refresh();
  sayConsequences([]);
  status(`${which}: ${entry.redo.map((m) => m.op).join(", ")} at frame ${entry.frame}`);
}

const undo = () => replay(state.history.takeUndo(), "undo");
const redo = () => replay(state.history.takeRedo(), "redo");

function dropHistory() {
  // another tab's edits: undoing from this page's older view of them could overwrite
  // them, so the history starts again
  state.history.done = [];
  state.history.undone = [];
}

async function toggleFixed() {
  // fixed: the robust triangulation always keeps this view's 2D of the point
  const s = selectedOrWarn();
  if (!s) return;
  const view = state.views.find((v) => v.name === s.view);
  const v = state.data.views[view.index];
  if (!v.points2d[s.point]) return status("only a placed point can be fixed");
  const fixed = !(v.fixed && v.fixed[s.point]);
  await sendEdit({ op: "move", view: s.view, point: s.point, xy: v.points2d[s.point], fixed });
  await refresh();
}

// -- item-level correction -------------------------------------------------------------

async function snapToGhost() {
  // c: the selected point onto its 3D ghost in its view (an Edit 2D move, undoable)
  const s = selectedOrWarn();
  if (!s || state.offline) return;
  const view = state.views.find((v) => v.name === s.view);
  const v = state.data.views[view.index];
  const ghost = v.reprojected[s.point];
  if (!ghost) return status(`${state.meta.points[s.point]} has no 3D at frame ${state.frame}: nothing to snap to`);
  const xy = [Math.min(view.width, Math.max(0, ghost[0])), Math.min(view.height, Math.max(0, ghost[1]))];
  if (await sendEdit({ op: "move", view: s.view, point: s.point, xy, fixed: Boolean(v.fixed && v.fixed[s.point]) })) {
    await refresh();
    status(`${state.meta.points[s.point]} in ${s.view} placed on its 3D ghost at frame ${state.frame}`);
  }
}

function currentItem(point) {
  // the item worked on (kept from n / p / a click), else the listed one at this frame
  if (state.item && state.item.point === point && state.item.frames.includes(state.frame)) return state.item;
  const listed = state.items.find((it) => it.point === point && it.frames.includes(state.frame));
  return listed ? { point, frames: [...listed.frames] } : null;
}

async function applyToItem() {
  // a: the selected point's edits in its view over the item's other frames, each frame
  // one journaled move; one undo takes them all back
  const s = selectedOrWarn();
  if (!s || state.offline) return;
  const item = currentItem(s.point);
  if (!item || item.frames.length < 2) return status("a: the selected point is in no suspect item of several frames here (pick one in the list, or n)");
  const view = state.views.find((v) => v.name === s.view);
  const data = {};
  for (const f of item.frames) data[f] = f === state.frame ? state.data : await getJSON(`/api/points/${f}`);
  const edited = {};
  for (const f of item.frames) {
    const v = data[f].views[view.index];
    if (v.edited[s.point] && v.points2d[s.point]) edited[f] = v.points2d[s.point];
  }
  const plan = itemPlan(item.frames, edited);
  const frames = Object.keys(plan).map(Number);
  if (!Object.keys(edited).length) return status(`a: correct ${state.meta.points[s.point]} in ${s.view} in at least one frame of the item first (drag it, or c: onto its 3D)`);
  if (!frames.length) return status("a: every frame of the item is already edited");
  const undo = [], redo = [];
  const results = [];
  for (const f of frames) {
    const v = data[f].views[view.index];
    const message = { op: "move", frame: f, view: s.view, point: s.point, xy: plan[f].map((c) => Math.round(c * 100) / 100),
      fixed: Boolean(v.fixed && v.fixed[s.point]) };
    const reply = await submit(message);
    if (!reply) break;
    undo.push(...restoreMessages(data[f], [s.point]));
    redo.push({ ...message, durable: true });
    results.push({ frame: f, error: reply.views[view.index].error[s.point], reply });
  }
  if (redo.length) state.history.record({ frame: state.frame, undo, redo });
  await refresh();
  sayConsequences(results.map((r) => r.reply));
  const shown = results.map((r) => `${r.frame}: ${r.error === null ? "dropped" : `${r.error.toFixed(1)} px`}`).join(", ");
  state.applied = { frames: results.map((r) => r.frame), errors: results.map((r) => r.error) };
  status(`applied to frames ${item.frames[0]}\u2013${item.frames[item.frames.length - 1]} of ${state.meta.points[s.point]} in ${s.view} ` +
    `(from edited ${Object.keys(edited).join(", ")}); reprojection error now ${shown}: step through them (\u2190 \u2192), Ctrl+Z undoes all`);
}

// -- review progress -------------------------------------------------------------------

function reviewItemHere(point) {
  // the review item of the selected point at this frame (the item worked on first)
  if (point === null || point === undefined) return null;
  const items = state.review ? state.review.items : [];
  return items.find((it) => it.point === point && it.frames.includes(state.frame)) ||
    (state.item && state.item.point === point && state.item.frames.includes(state.frame) ? state.item : null);
}

async function markReviewed() {
  // k: the selected point's item reviewed / OK at every frame of it (again: unmarked),
  // journaled and undoable like an edit; then the next unreviewed item
  const s = selectedOrWarn();
  if (!s || state.offline) return;
  const item = reviewItemHere(s.point);
  if (!item) return status(`k: ${state.meta.points[s.point]} is in no suspect item at frame ${state.frame}`);
  const mark = !(state.data.reviewed && state.data.reviewed[s.point]);
  const op = mark ? "reviewed" : "unreviewed", back = mark ? "unreviewed" : "reviewed";
  const redo = [], undo = [];
  for (const f of item.frames) {
    const message = { op, frame: f, point: s.point };
    if (!(await submit(message))) break;
    redo.push({ ...message, durable: true });
    undo.push({ op: back, frame: f, point: s.point });
  }
  if (redo.length) state.history.record({ frame: state.frame, undo, redo });
  await refresh();
  status(`${state.meta.points[s.point]} at frames ${item.frames.join(", ")} ${mark ? "marked reviewed" : "no longer marked reviewed"}` +
    ` (${state.review.done} / ${state.review.total} reviewed)`);
  if (mark) await nextUnreviewed(true);
}

async function nextUnreviewed(quiet = false) {
  // u: the next item not yet reviewed (nor corrected), best first, after the current one
  const items = state.review ? state.review.items : [];
  const open = items.filter((it) => !it.done);
  if (!open.length) { if (!quiet) status(`every suspect item is reviewed (${state.review.done} / ${state.review.total})`); return; }
  let here = items.findIndex((it) => state.selected && it.point === state.selected.point && it.frames.includes(state.frame));
  if (here < 0 && state.item) here = items.findIndex((it) => sameItem(it, state.item));  // off it: after it
  await jumpToSuspect(items.slice(here + 1).find((it) => !it.done) || open[0]);
}

async function refresh() {
  // the server's current state of this frame and the suspects (re-found once an edit is
  // done, not on every drag step)
  const frame = state.frame;
  const data = await getJSON(`/api/points/${frame}`);
  if (frame === state.frame) state.data = data;
  state.revision = data.revision;
  await loadSuspects();
  redrawAll();
}

function changedElsewhere(message) {
  if (message.revision === state.revision) return;
  dropHistory();
  status(`another tab changed the edits (revision ${message.revision}); this page was refreshed`);
  if (!state.dragging) refresh();
}

function serverLost() {
  state.offline = true;
  state.mode = "view";
  state.editMode = false;
  document.body.classList.add("offline");
  const dirty = state.data && state.data.dirty;
  showAlert("flylib gui has stopped: edits are no longer accepted. Every edit it confirmed " +
    `is ${dirty ? "journaled on disk (not yet saved) and replayed" : "saved and loaded"} when ` +
    "`flylib gui` runs again; this page reloads then.");
  const probe = setInterval(async () => {
    try {
      const response = await fetch(apiUrl("/api/meta"), { cache: "no-store" });
      if (response.ok) { clearInterval(probe); location.reload(); }
    } catch { /* still gone */ }
  }, 2000);
}

function selectedOrWarn() {
  if (!state.selected) { status("select a point first (click it)"); return null; }
  return state.selected;
}

async function markInvisible() {
  const s = selectedOrWarn();
  if (s) { await sendEdit({ op: "invisible", view: s.view, point: s.point }); await refresh(); }
}

async function resetPoint(everywhere = false) {
  const s = selectedOrWarn();
  if (!s) return;
  await sendEdit(everywhere ? { op: "reset_point", point: s.point } : { op: "reset_point", view: s.view, point: s.point });
  await refresh();
}

function setMode(mode) {
  if (state.offline) return;
  state.mode = state.mode === mode ? "view" : mode;
  state.editMode = state.mode !== "view";
  document.querySelector(`input[name=mode][value="${state.mode === "view" ? "view" : state.mode}"]`).checked = true;
}

async function resetView() {
  const view = state.selected ? state.selected.view : state.views[state.focus].name;
  await sendEdit({ op: "reset_view", view });
  await refresh();
}

async function resetFrame() {
  await sendEdit({ op: "reset_frame" });
  await refresh();
}

async function save(checked = false) {
  // first what the edits made worse (a point farther from its 3D, new suspects): said
  // in a dialog, saved only on "Save anyway"
  if (state.offline) return;
  if (!checked) {
    const check = await getJSON("/api/save-check");
    if (check.count > 0) return showSaveCheck(check);
  }
  $("#save-check").hidden = true;
  let reply;
  try {
    reply = await postJSON("/api/save", { revision: state.revision });
  } catch (err) {
    if (err.status === 409) {
      await refresh();
      status(`not saved: ${err.detail}`);
    } else {
      showAlert(`not saved: ${err.detail || err.message}`);
    }
    return;
  }
  // a failed save's alert, or the replayed journal's "press Save": said and done
  if (alertText().startsWith("not saved") || alertText() === state.meta.notice) clearAlert();
  state.revision = reply.revision;
  status(`saved ${reply.edits} edits to ${reply.saved}; run snakemake to apply them`);
  if (state.data) Object.assign(state.data, { dirty: false, unsaved: 0 });
  redrawAll();
  window.flylib.saved = reply;
}

function showSaveCheck(check) {
  const box = $("#save-check");
  const list = box.querySelector("ul");
  const lines = [...check.worse.map((t) => `made worse: ${t}`), ...check.new_suspects.map((t) => `new suspect: ${t}`)];
  const items = lines.map((text, i) => {
    // a click goes to the line's frame (the dialog closes; s asks again)
    const li = document.createElement("li");
    li.textContent = text;
    li.className = "clickable";
    li.title = `go to frame ${check.frames[i]}`;
    li.addEventListener("click", () => { box.hidden = true; act(() => goto(check.frames[i])); });
    return li;
  });
  const more = check.count - lines.length;
  if (more > 0) items.push(Object.assign(document.createElement("li"), { textContent: `and ${more} more` }));
  list.replaceChildren(...items);
  box.hidden = false;
  $("#save-anyway").focus();
  status(`not saved yet: ${check.count} edit result(s) to look at first`);
}

function attachMouse(view) {
  const canvas = view.canvas;
  let drag = null;
  const local = (event) => {
    const rect = canvas.getBoundingClientRect();
    const dpr = canvas.width / rect.width;
    return [(event.clientX - rect.left) * dpr, (event.clientY - rect.top) * dpr];
  };
  canvas.addEventListener("mousedown", (event) => {
    event.preventDefault();
    const [cx, cy] = local(event);
    const hit = nearestPoint(view, cx, cy);
    if (state.layout === "focus" && view.index !== state.focus) {
      setFocus(view.index);  // a thumbnail: click makes it the large view
      return;
    }
    if (hit !== null) {
      state.selected = { view: view.name, point: hit };
      redrawAll();
      if (state.mode !== "view" && event.button === 0 && !state.offline) {
        drag = { kind: "point", point: hit, sending: false, pending: null, before: restoreMessages(state.data, [hit]) };
        state.dragging = true;
      } else {
        return;  // a press on a point selects it; it never pans the view
      }
    }
    if (!drag) drag = { kind: "pan", start: [cx, cy], zoom: { ...state.zoom[view.name] } };
  });
  canvas.addEventListener("mousemove", (event) => {
    if (drag || !state.data) return;
    const [cx, cy] = local(event);
    const hit = nearestPoint(view, cx, cy);
    const before = state.hover;
    state.hover = hit === null ? null : { view: view.name, point: hit };
    canvas.title = hit === null ? `${view.index + 1} ${view.name}` : `${state.meta.points[hit]} (${view.index + 1} ${view.name})`;
    if ((before && before.point) !== (state.hover && state.hover.point) || (before && before.view) !== view.name) draw(view);
  });
  canvas.addEventListener("mouseleave", () => { if (state.hover && state.hover.view === view.name) { state.hover = null; draw(view); } });
  window.addEventListener("mousemove", async (event) => {
    if (!drag || !state.data) return;
    const [cx, cy] = local(event);
    if (drag.kind === "pan") {
      const z = state.zoom[view.name];
      z.x = drag.zoom.x + cx - drag.start[0];
      z.y = drag.zoom.y + cy - drag.start[1];
      draw(view);
      return;
    }
    const xy = toImage(view.transform, cx, cy);
    drag.moved = true;
    // follow the mouse at once: the 2D point (Edit 2D) or the 3D ghost (Edit 3D)
    state.data.views[view.index][state.mode === "3d" ? "reprojected" : "points2d"][drag.point] = xy;
    draw(view);
    drag.pending = xy;
    if (!drag.sending) await flushDrag(view, drag);
  });
  window.addEventListener("mouseup", async (event) => {
    if (!drag) return;
    const finished = drag;
    drag = null;
    if (finished.kind === "point" && !finished.moved) {
      state.dragging = false;  // a click selects; only a drag edits
    } else if (finished.kind === "point") {
      const [cx, cy] = local(event);
      finished.pending = toImage(view.transform, cx, cy);
      finished.final = true;
      if (!finished.sending) await flushDrag(view, finished);
    }
  });
  canvas.addEventListener("wheel", (event) => {
    event.preventDefault();
    const [cx, cy] = local(event);
    const z = state.zoom[view.name];
    const factor = Math.exp(-event.deltaY * 0.0015);
    const scale = Math.min(40, Math.max(1, z.scale * factor));
    // keep the image pixel under the cursor in place
    const [u, v] = toImage(view.transform, cx, cy);
    const base = fitTransform(canvas, view.width, view.height, { scale: 1, x: 0, y: 0 });
    z.x = cx - u * base.scale * scale - base.ox * scale;
    z.y = cy - v * base.scale * scale - base.oy * scale;
    z.scale = scale;
    draw(view);
  }, { passive: false });
  canvas.addEventListener("dblclick", () => { state.zoom[view.name] = { scale: 1, x: 0, y: 0 }; draw(view); });
}

async function flushDrag(view, drag) {
  // one move in flight at a time; the latest position wins
  drag.sending = true;
  actions.sending++;
  showBusy();
  while (drag.pending) {
    const xy = drag.pending;
    drag.pending = null;
    // the drag's last position is fsync'd on the server; the ones before are only flushed
    const durable = Boolean(drag.final);
    const was = state.data.views[view.index];
    const message = state.mode === "3d" ? { op: "move3d", view: view.name, point: drag.point, xy, durable }
      : { op: "move", view: view.name, point: drag.point, xy, durable, fixed: Boolean(was.fixed && was.fixed[drag.point]) };
    await sendEdit(message, drag);
  }
  drag.sending = false;
  if (drag.final) {
    await refresh();
    state.dragging = false;
  }
  actions.sending--;
  showBusy();
}

function nearestPoint(view, cx, cy) {
  if (!state.data || !view.transform) return null;
  const v = state.data.views[view.index];
  const dpr = window.devicePixelRatio || 1;
  let best = null, bestD = 12 * dpr;
  v.points2d.forEach((p, i) => {
    if (state.display.limb !== null && state.meta.point_limbs[i] !== state.display.limb) return;
    // the 2D point, or the 3D ghost (Edit 3D, or where the point is invisible in this view)
    const ghost = state.mode === "3d" || v.invisible[i] || !p ? v.reprojected[i] : null;
    for (const q of [p, ghost]) {
      if (!q) continue;
      const [x, y] = toCanvas(view.transform, q);
      const d = Math.hypot(x - cx, y - cy);
      if (d < bestD) { best = i; bestD = d; }
    }
  });
  return best;
}

// -- layout and keys ----------------------------------------------------------------

function setLayout(layout) {
  state.layout = layout;
  $("#views").className = layout;
  setFocus(state.focus);
}

const FOCUS_ZOOM = 2.5;  // a focused point's view: the frame magnified around the point

function focusOn(view, point) {
  // the selected point's view large, every view zoomed to the point (g, n / p, a click in the list)
  state.layout = "focus";
  $("#views").className = "focus";
  setFocus(view.index);
  requestAnimationFrame(() => {
    for (const v of state.views) {
      resize(v);
      const xy = pointAt(state.data, v, point);
      if (xy) zoomTo(v, xy, FOCUS_ZOOM); else state.zoom[v.name] = { scale: 1, x: 0, y: 0 };
    }
    redrawAll();
  });
}

function zoomTo(view, xy, scale) {
  // zoom and pan `view` so that image point xy lies at the canvas centre
  const canvas = view.canvas;
  const fit = Math.min(canvas.width / view.width, canvas.height / view.height);
  const z = state.zoom[view.name];
  z.scale = scale;
  z.x = canvas.width / 2 - xy[0] * fit * scale - (canvas.width - view.width * fit) / 2 * scale;
  z.y = canvas.height / 2 - xy[1] * fit * scale - (canvas.height - view.height * fit) / 2 * scale;
}

function toggleFocus() {
  // g: the selected point's view, zoomed to it (else view 1); again: back to the grid
  if (state.layout === "focus") return setLayout("grid");
  const s = state.selected;
  const view = s ? state.views.find((v) => v.name === s.view) : state.views[0];
  if (s) focusOn(view, s.point); else { state.focus = 0; setLayout("focus"); }
}

function setPanel(open) {
  // the side panel (selection, suspects, legend, display): hidden, the views take its room
  document.body.classList.toggle("panel-closed", !open);
  $("#panel").classList.toggle("active", open);
  try { localStorage.setItem("flylib.panel", open ? "open" : "closed"); } catch { /* private mode */ }
  relayout();
  requestAnimationFrame(redrawAll);
}

// views, then the 3D view (index = number of views) in the focus layout

function setFocus(index) {
  state.focus = Math.max(0, Math.min(state.views.length, index));
  const tiles = [...state.views.map((v) => v.div), state.tile3d];
  tiles.forEach((div, i) => div.classList.toggle("large", state.layout === "focus" && i === state.focus));
  relayout();  // CSS order only: thumbnails keep their order and their canvases
  requestAnimationFrame(redrawAll);
}

function toggleHelp(show) {
  const help = $("#help");
  help.hidden = show === undefined ? !help.hidden : !show;
}

function wireControls() {
  document.querySelectorAll("input[name=mode]").forEach((input) => input.addEventListener("change", () => {
    state.mode = state.offline ? "view" : input.value;
    state.editMode = state.mode !== "view";
  }));
  $("#layout").addEventListener("click", toggleFocus);
  $("#panel").addEventListener("click", () => setPanel(document.body.classList.contains("panel-closed")));
  $("#invisible").addEventListener("click", () => act(markInvisible));
  $("#reset-point").addEventListener("click", () => act(() => resetPoint(false)));
  $("#reset-view").addEventListener("click", () => act(resetView));
  $("#reset-frame").addEventListener("click", () => act(resetFrame));
  $("#save").addEventListener("click", () => act(save));
  $("#save-anyway").addEventListener("click", () => act(() => save(true)));
  $("#save-cancel").addEventListener("click", () => { $("#save-check").hidden = true; status("not saved"); });
  $("#undo").addEventListener("click", () => act(undo));
  $("#redo").addEventListener("click", () => act(redo));
  $("#fixed").addEventListener("click", () => act(toggleFixed));
  $("#snap").addEventListener("click", () => act(snapToGhost));
  $("#reviewed").addEventListener("click", () => act(markReviewed));
  $("#next-unreviewed").addEventListener("click", () => act(() => nextUnreviewed()));
  $("#apply-item").addEventListener("click", () => act(applyToItem));
  state.tile3d.addEventListener("mousedown", () => { if (state.layout === "focus" && state.focus !== state.views.length) setFocus(state.views.length); });
  $("#frame-input").addEventListener("change", () => {
    const text = $("#frame-input").value.trim();
    const last = state.meta.frames - 1;
    if (!/^\d+$/.test(text)) { status(`"${text}" is not a frame number (0..${last})`); return; }
    if (Number(text) > last) status(`frame ${text} is past the last frame; showing frame ${last}`);
    goto(Number(text));
  });
  $("#frame-input").addEventListener("keydown", (event) => { if (event.key === "Enter") $("#frame-input").blur(); });
  window.addEventListener("beforeunload", (event) => {
    // unsaved edits: the browser asks before leaving (its own words; the text is ignored)
    if (state.data && state.data.dirty) { event.preventDefault(); event.returnValue = ""; }
  });
  $("#help-button").addEventListener("click", () => toggleHelp());
  $("#next-suspect").addEventListener("click", () => act(() => stepSuspect(1)));
  $("#prev-suspect").addEventListener("click", () => act(() => stepSuspect(-1)));
  document.querySelectorAll("#suspects th").forEach((th) => th.addEventListener("click", () => {
    const key = th.dataset.key;
    state.sort = { key, asc: state.sort.key === key ? !state.sort.asc : key !== "score" };
    renderSuspectTable();
  }));
  $("#timeline").addEventListener("click", (event) => {
    const rect = event.target.getBoundingClientRect();
    goto(Math.floor((event.clientX - rect.left) / rect.width * state.meta.frames));
  });
  window.addEventListener("resize", () => { $("#timeline").width = $("#timeline").clientWidth; redrawAll(); });
  window.addEventListener("keyup", (event) => {
    if (event.key === "h" && state.peek) { state.peek = false; redrawAll(); }  // hold h: peek
  });
  window.addEventListener("blur", () => { if (state.peek) { state.peek = false; redrawAll(); } });
  $("#play").addEventListener("click", togglePlay);
  $("#fps").addEventListener("change", () => {
    const raw = $("#fps").value, fps = Math.max(1, Math.min(120, Math.round(Number(raw) || 10)));
    if (String(fps) !== raw) status(`fps "${raw}" is not a whole number from 1 to 120; playing at ${fps}`);
    $("#fps").value = String(fps);
  });
  $("#stop-server").addEventListener("click", stopServer);
  $("#reload-results").addEventListener("click", () => act(reloadResults));
  window.addEventListener("keydown", (event) => {
    if (event.target.tagName === "INPUT" && event.target.type !== "range" && event.target.type !== "checkbox") return;
    if ((event.ctrlKey || event.metaKey) && (event.key === "z" || event.key === "Z" || event.key === "y")) {
      event.preventDefault();
      act(event.key === "y" || event.shiftKey ? redo : undo);
      return;
    }
    const big = event.shiftKey ? 10 : 1;
    const key = event.key;
    // what reads or changes the frame, the selection or the edits waits its turn
    const queued = {
      Home: () => goto(0), End: () => goto(state.meta.frames - 1),
      n: () => stepSuspect(1), p: () => stepSuspect(-1), e: () => setMode("2d"), d: () => setMode("3d"),
      i: markInvisible, c: snapToGhost, k: markReviewed, u: () => nextUnreviewed(), a: applyToItem,
      f: toggleFixed, r: () => resetPoint(false), R: () => resetPoint(true), v: resetView, x: resetFrame,
      g: toggleFocus, s: () => save(),
    };
    if (key === "ArrowRight" || key === "ArrowLeft") act(null, key === "ArrowRight" ? big : -big);
    else if (Object.hasOwn(queued, key)) act(queued[key]);
    else if (key === "S" && event.ctrlKey) act(queued.s);
    else if (key >= "1" && key <= "9" && Number(key) <= state.views.length + 1) act(() => { if (state.layout !== "focus") setLayout("focus"); setFocus(Number(key) - 1); });
    else if (key === "o") setDisplay({ overlay: !state.display.overlay });
    else if (key === "l") setDisplay({ labels: !state.display.labels });
    else if (key === "h") { if (!state.peek) { state.peek = true; redrawAll(); } }
    else if (key === "[") cycleLimb(-1);
    else if (key === "]") cycleLimb(1);
    else if (key === " ") togglePlay();
    else if (key === "b") setPanel(document.body.classList.contains("panel-closed"));
    else if (key === "0") { for (const v of state.views) state.zoom[v.name] = { scale: 1, x: 0, y: 0 }; redrawAll(); }
    else if (key === "?") toggleHelp();
    else if (key === "Escape") { toggleHelp(false); $("#save-check").hidden = true; }
    else return;
    event.preventDefault();
  });
}

// A small handle for scripted checks (the browser test): where a point is on screen,
// and whether every canvas shows the current frame.
window.flylib = {
  state,
  goto,
  stepSuspect,
  alert: alertText,
  busy: () => actions.running || channel.busy || state.dragging,
  allDrawn: () => state.views.length > 0 && state.views.every((v) => v.canvas.dataset.drawnFrame === String(state.frame)),
  undo,
  redo,
  history: () => ({ undo: state.history.done.length, redo: state.history.undone.length }),
  cellFill() {
    // per view: the fraction of its tile the frame covers (unzoomed), and the tiles' boxes
    return state.views.map((view) => {
      const rect = view.div.getBoundingClientRect();
      const fit = Math.min(rect.width / view.width, rect.height / view.height);
      return { name: view.name, fill: (view.width * fit * view.height * fit) / (rect.width * rect.height),
        left: rect.left, top: rect.top, width: rect.width, height: rect.height };
    });
  },
  focusFill() {
    // the large view's frame (unzoomed) less what the thumbnails cover, as a fraction of the window
    const view = state.views[state.focus];
    if (state.layout !== "focus" || !view) return 0;
    const r = view.canvas.getBoundingClientRect();
    const fit = Math.min(r.width / view.width, r.height / view.height);
    const w = view.width * fit, h = view.height * fit, left = r.left + (r.width - w) / 2, top = r.top + (r.height - h) / 2;
    let covered = 0;
    for (const tile of [...state.views.map((v) => v.div), state.tile3d]) {
      const t = tile === view.div ? null : tile.getBoundingClientRect();
      if (t) covered += Math.max(0, Math.min(t.right, left + w) - Math.max(t.left, left)) * Math.max(0, Math.min(t.bottom, top + h) - Math.max(t.top, top));
    }
    return (w * h - covered) / (window.innerWidth * window.innerHeight);
  },
  tile3d: () => { const r = state.tile3d.getBoundingClientRect(); return { left: r.left, top: r.top, width: r.width, height: r.height, drawnFrame: state.tile3d.querySelector("canvas").dataset.drawnFrame }; },
  screenPosition(viewName, point) {
    const view = state.views.find((v) => v.name === viewName);
    const p = state.data.views[view.index].points2d[point];
    if (!p) return null;
    const [x, y] = toCanvas(view.transform, p);
    const rect = view.canvas.getBoundingClientRect();
    const dpr = view.canvas.width / rect.width;
    return { x: x / dpr, y: y / dpr, left: rect.left, top: rect.top, width: rect.width, height: rect.height };
  },
  saved: null,
};

start().catch((err) => { status(`failed to start: ${err.message}`); console.error(err); });
