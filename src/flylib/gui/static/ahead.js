// Frames fetched ahead of the user: each view's image (decoded) and the frame's points, two
// frames at a time after the shown one's requests, so a step or a playback tick finds them.

import { apiUrl, getJSON } from "./api.js";

const PARALLEL = 2;  // frames fetched ahead at once (2 requests each)
const KEEP = 32;  // frames held (7 views x 1.8 MB decoded each at 960 x 480)

export class FramesAhead {
  constructor(views) {
    this.views = views;  // view names
    this.frames = new Map();  // frame -> {images: {view: Promise of an ImageBitmap}, points, ready}
    this.queue = [];
    this.loading = 0;  // frames being fetched ahead
  }

  usable(frame, small) {
    // the frame's entry if here, at full size unless small (playback) will do
    return small || !this.frames.get(frame)?.small ? this.frames.get(frame) : undefined;
  }

  get(frame, small) {
    // the frame's entry, fetched now unless it is already here
    const entry = this.usable(frame, small) || this.load(frame, small);
    this.frames.delete(frame);
    this.frames.set(frame, entry);  // most recently used last
    return entry;
  }

  isReady(frame) {
    return Boolean(this.frames.get(frame)?.done);
  }

  load(frame, small) {
    // the views' JPEGs in one response (a request cost the browser more than a decode), decoded
    // into ImageBitmaps (an Image's pixels may be dropped until drawn, and decoded again);
    // small: at half size where the server has it (playback: a quarter of the pixels to decode)
    const parts = fetch(apiUrl(`/api/frames/${frame}${small ? "?small=1" : ""}`)).then(async (r) => {
      const lengths = r.ok ? r.headers.get("X-Lengths").split(",").map(Number) : [], blob = await r.blob();
      let at = 0;
      return lengths.map((n) => blob.slice(at, (at += n), "image/jpeg"));
    });
    const images = {};
    this.views.forEach((view, i) => { images[view] = parts.then((p) => p[i] && createImageBitmap(p[i])).catch(() => null); });
    const points = getJSON(`/api/points/${frame}`);
    points.catch(() => this.frames.delete(frame));  // a failed read is asked again
    const entry = { images, points, small, ready: Promise.all([...Object.values(images), points.catch(() => {})]) };
    entry.ready.then(() => { entry.done = true; });
    this.frames.set(frame, entry);
    while (this.frames.size > KEEP) this.frames.delete(this.frames.keys().next().value);
    return entry;
  }

  want(frames, small) {
    // fetch these frames, nearest first, PARALLEL at a time (the rest of an older list dropped)
    [this.queue, this.small] = [frames.filter((f) => !this.usable(f, small)), small];
    const next = () => {
      const f = this.queue.shift();
      if (f === undefined) { this.loading--; return; }
      (this.usable(f, this.small) ? Promise.resolve() : this.load(f, this.small).ready).then(next);
    };
    while (this.loading < PARALLEL && this.queue.length) { this.loading++; next(); }
  }
}
