// The 3D view (the seed GUI's rig-and-pose panel): the current frame's 3D skeleton and
// the cameras, orthographic, drag to turn, wheel to zoom, double-click to reset.
// "fly" scale (default) fits the fly and draws each camera on a ring around it in its
// true direction (the rig is ~20 times the fly); "rig" scale draws true positions.

export class View3D {
  constructor(canvas, meta, onPick) {
    this.canvas = canvas;
    this.meta = meta;
    this.yaw = -0.6;
    this.pitch = 0.45;
    this.zoom = 1;
    this.scaleMode = "fly";
    this.points = null;
    this.selected = null;
    this.drawnFrame = null;
    this.onPick = onPick;
    this.screen = [];  // [x, y, point] of the drawn points, for hover and picking
    let drag = null;
    canvas.addEventListener("mousedown", (e) => { drag = { x: e.clientX, y: e.clientY, yaw: this.yaw, pitch: this.pitch, moved: false }; });
    window.addEventListener("mousemove", (e) => {
      if (drag) {
        drag.moved = drag.moved || Math.hypot(e.clientX - drag.x, e.clientY - drag.y) > 3;
        this.yaw = drag.yaw + (e.clientX - drag.x) * 0.01;
        this.pitch = Math.max(-1.5, Math.min(1.5, drag.pitch + (e.clientY - drag.y) * 0.01));
        this.draw();
      } else if (e.target === canvas) {
        const hit = this.pick(e);
        canvas.title = hit === null ? "3D view: drag to turn, wheel to zoom" : this.meta.points[hit];
      }
    });
    window.addEventListener("mouseup", (e) => {
      if (drag && !drag.moved && e.target === canvas) {
        const hit = this.pick(e);
        if (hit !== null && this.onPick) this.onPick(hit);
      }
      drag = null;
    });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoom = Math.min(50, Math.max(0.05, this.zoom * Math.exp(-e.deltaY * 0.0015)));
      this.draw();
    }, { passive: false });
    canvas.addEventListener("dblclick", () => { this.yaw = -0.6; this.pitch = 0.45; this.zoom = 1; this.draw(); });
  }

  toggleScale() {
    this.scaleMode = this.scaleMode === "fly" ? "rig" : "fly";
    this.zoom = 1;
    this.draw();
    return this.scaleMode;
  }

  pick(event) {
    const rect = this.canvas.getBoundingClientRect();
    const dpr = this.canvas.width / Math.max(rect.width, 1);
    const x = (event.clientX - rect.left) * dpr, y = (event.clientY - rect.top) * dpr;
    let best = null, bestD = 10 * dpr;
    for (const [sx, sy, p] of this.screen) {
      const d = Math.hypot(sx - x, sy - y);
      if (d < bestD) { best = p; bestD = d; }
    }
    return best;
  }

  update(data, selected) {
    this.points = data ? data.points3d : null;
    this.frame = data ? data.frame : null;
    this.selected = selected;
    this.draw();
  }

  rotate(p) {
    // world (x forward, y left, z up) -> screen: yaw about z, pitch about the screen x axis
    const cy = Math.cos(this.yaw), sy = Math.sin(this.yaw), cp = Math.cos(this.pitch), sp = Math.sin(this.pitch);
    const x = cy * p[0] - sy * p[1], y = sy * p[0] + cy * p[1], z = p[2];
    return [x, -(cp * z - sp * y), sp * z + cp * y];  // screen x, screen y (down), depth
  }

  draw() {
    const canvas = this.canvas, meta = this.meta;
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#0b0d10";
    ctx.fillRect(0, 0, w, h);
    this.screen = [];
    const pts = (this.points || []).map((p) => p && p.every(Number.isFinite) ? p : null);
    const have = pts.filter(Boolean);
    const rig = meta.rig || [];
    let centre = [0, 0, 0], extent = 1;
    if (have.length) {
      centre = [0, 1, 2].map((k) => have.reduce((s, p) => s + p[k], 0) / have.length);
      extent = Math.max(1e-6, ...have.map((p) => Math.hypot(p[0] - centre[0], p[1] - centre[1], p[2] - centre[2])));
    }
    const cams = rig.map((c) => {
      const d = [0, 1, 2].map((k) => c.position[k] - centre[k]);
      const dist = Math.hypot(...d) || 1;
      const ring = this.scaleMode === "fly" ? 1.6 * extent / dist : 1;
      return { ...c, dist, at: [0, 1, 2].map((k) => centre[k] + d[k] * ring) };
    });
    if (this.scaleMode === "rig" && cams.length) extent = Math.max(extent, ...cams.map((c) => c.dist));
    else extent *= 1.6;
    const scale = 0.45 * Math.min(w, h) / extent * this.zoom;
    const toScreen = (p) => {
      const r = this.rotate([p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]]);
      return [w / 2 + r[0] * scale, h / 2 + r[1] * scale, r[2]];
    };
    // the ground axes at the fly: x red, y green, z blue, one body extent long
    ctx.lineWidth = 1 * dpr;
    [[1, 0, 0, "#a33"], [0, 1, 0, "#3a3"], [0, 0, 1, "#36c"]].forEach(([x, y, z, color]) => {
      const a = toScreen(centre), b = toScreen([centre[0] + x * extent * 0.3, centre[1] + y * extent * 0.3, centre[2] + z * extent * 0.3]);
      ctx.strokeStyle = color;
      line(ctx, a, b);
    });
    // cameras: a dot, a line towards where they look, the tile's name (no names in a thumbnail:
    // at ~100 px they cover its title and each other)
    ctx.font = `${11 * dpr}px system-ui, sans-serif`;
    const named = w >= 200 * dpr;
    cams.forEach((c, i) => {
      const a = toScreen(c.at);
      const look = [0, 1, 2].map((k) => c.at[k] + c.axis[k] * extent * 0.25);
      ctx.strokeStyle = "#9ab";
      line(ctx, a, toScreen(look));
      ctx.fillStyle = "#dde";
      ctx.beginPath();
      ctx.arc(a[0], a[1], 3.5 * dpr, 0, 2 * Math.PI);
      ctx.fill();
      if (named) ctx.fillText(`${i + 1} ${c.name}`, a[0] + 5 * dpr, a[1] - 5 * dpr);
    });
    // the skeleton, far bones first
    const scr = pts.map((p) => p ? toScreen(p) : null);
    const bones = meta.bones.map(([a, b], i) => ({ a, b, i, depth: scr[a] && scr[b] ? scr[a][2] + scr[b][2] : null }))
      .filter((x) => x.depth !== null).sort((x, y) => y.depth - x.depth);
    ctx.lineWidth = 2 * dpr;
    for (const { a, b, i } of bones) {
      ctx.strokeStyle = meta.bone_colors[i];
      line(ctx, scr[a], scr[b]);
    }
    scr.forEach((s, p) => {
      if (!s) return;
      ctx.fillStyle = meta.point_colors[p];
      ctx.beginPath();
      ctx.arc(s[0], s[1], 2.5 * dpr, 0, 2 * Math.PI);
      ctx.fill();
      this.screen.push([s[0], s[1], p]);
      if (p === this.selected) {
        ctx.strokeStyle = "#6aa0ff";
        ctx.lineWidth = 1.5 * dpr;
        ctx.beginPath();
        ctx.arc(s[0], s[1], 7 * dpr, 0, 2 * Math.PI);
        ctx.stroke();
        ctx.fillStyle = "#fff";
        if (named) ctx.fillText(meta.points[p], s[0] + 9 * dpr, s[1] + 4 * dpr);
      }
    });
    if (!have.length) {
      ctx.fillStyle = "#889";
      ctx.fillText("no 3D at this frame", 8 * dpr, h - 8 * dpr);
    }
    this.drawnFrame = this.frame;
    canvas.dataset.drawnFrame = this.frame === null ? "" : String(this.frame);
  }
}

function line(ctx, a, b) {
  ctx.beginPath();
  ctx.moveTo(a[0], a[1]);
  ctx.lineTo(b[0], b[1]);
  ctx.stroke();
}
