// Drawing one camera view on its canvas: footage, 2D skeleton, reprojected 3D ghost.

export function fitTransform(canvas, width, height, zoom) {
  // image pixel -> canvas pixel: fit the frame, then the view's own zoom/pan
  const fit = Math.min(canvas.width / width, canvas.height / height);
  const scale = fit * zoom.scale;
  const ox = (canvas.width - width * fit) / 2 * zoom.scale + zoom.x;
  const oy = (canvas.height - height * fit) / 2 * zoom.scale + zoom.y;
  return { scale, ox, oy };
}

export function toCanvas(t, xy) { return [t.ox + xy[0] * t.scale, t.oy + xy[1] * t.scale]; }
export function toImage(t, cx, cy) { return [(cx - t.ox) / t.scale, (cy - t.oy) / t.scale]; }

export function drawView(canvas, image, view, meta, data, options) {
  const ctx = canvas.getContext("2d");
  const dpr = window.devicePixelRatio || 1;
  const t = fitTransform(canvas, view.width, view.height, options.zoom);
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#000";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (image) {  // an ImageBitmap
    const filter = options.filter && options.filter !== "none";
    if (filter) ctx.filter = options.filter;  // brightness / contrast / gamma of the footage
    ctx.drawImage(image, t.ox, t.oy, view.width * t.scale, view.height * t.scale);
    if (filter) ctx.filter = "none";
  }
  if (!data || options.peek) return t;  // hold h: the footage alone
  const v = data.views[options.viewIndex];
  // the one-limb filter: the other limbs' points are not drawn
  const shown = (i) => options.limb === null || options.limb === undefined || meta.point_limbs[i] === options.limb;
  const pts = v.points2d.map((p, i) => (shown(i) ? p : null));
  const ghost = options.overlay === false ? pts.map(() => null) : v.reprojected.map((p, i) => (shown(i) ? p : null));
  const r = Math.max(2.5, 3.5 * dpr);
  // ghost: the 3D reprojected, thin lines and crosses
  ctx.lineWidth = 1 * dpr;
  ctx.setLineDash([4 * dpr, 3 * dpr]);
  meta.bones.forEach(([a, b], i) => {
    if (!ghost[a] || !ghost[b]) return;
    ctx.strokeStyle = meta.bone_colors[i] + "99";
    line(ctx, toCanvas(t, ghost[a]), toCanvas(t, ghost[b]));
  });
  ctx.setLineDash([]);
  ghost.forEach((p, i) => {
    if (!p) return;
    const [x, y] = toCanvas(t, p);
    ctx.strokeStyle = meta.point_colors[i];
    line(ctx, [x - r, y - r], [x + r, y + r]);
    line(ctx, [x - r, y + r], [x + r, y - r]);
  });
  // the 2D triangulation reads (their bones hidden with the overlay)
  ctx.lineWidth = 2 * dpr;
  meta.bones.forEach(([a, b], i) => {
    if (options.overlay === false || !pts[a] || !pts[b]) return;
    ctx.strokeStyle = meta.bone_colors[i];
    line(ctx, toCanvas(t, pts[a]), toCanvas(t, pts[b]));
  });
  const suspect = new Set(data.suspects.map((s) => s.point));
  pts.forEach((p, i) => {
    const invisible = v.invisible[i];
    if (!p) {
      if (invisible && v.reprojected[i] && shown(i)) {  // an invisible point shows where the 3D puts it
        const [x, y] = toCanvas(t, v.reprojected[i]);
        ctx.strokeStyle = "#fff";
        ctx.lineWidth = 1.5 * dpr;
        ctx.strokeRect(x - r * 1.6, y - r * 1.6, r * 3.2, r * 3.2);
      }
      return;
    }
    const [x, y] = toCanvas(t, p);
    ctx.beginPath();
    ctx.arc(x, y, r, 0, 2 * Math.PI);
    if (v.used[i]) {
      ctx.fillStyle = meta.point_colors[i];
      ctx.fill();
    } else {
      ctx.strokeStyle = meta.point_colors[i];
      ctx.lineWidth = 1.5 * dpr;
      ctx.stroke();
    }
    if (v.edited[i]) ring(ctx, x, y, r * 2, "#ffffff", dpr);
    if (suspect.has(i)) ring(ctx, x, y, r * 2.8, "#ff4040", dpr);
    if (options.selected === i) ring(ctx, x, y, r * 3.6, "#6aa0ff", dpr);
  });
  return t;
}

function line(ctx, a, b) {
  ctx.beginPath();
  ctx.moveTo(a[0], a[1]);
  ctx.lineTo(b[0], b[1]);
  ctx.stroke();
}

function ring(ctx, x, y, radius, color, dpr) {
  ctx.beginPath();
  ctx.arc(x, y, radius, 0, 2 * Math.PI);
  ctx.strokeStyle = color;
  ctx.lineWidth = 1.5 * dpr;
  ctx.stroke();
}

export function drawTimeline(canvas, frameScore, suspectFrames, current) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, n = frameScore.length;
  ctx.fillStyle = "#111";
  ctx.fillRect(0, 0, w, h);
  const step = w / Math.max(n, 1);
  const top = Math.max(1, ...frameScore);
  frameScore.forEach((s, i) => {
    if (s <= 0) return;
    const bar = Math.max(3, (h - 4) * Math.min(s, top) / top);
    ctx.fillStyle = suspectFrames.has(i) ? "#e04848" : "#777";
    ctx.fillRect(i * step, h - bar, Math.max(step - 1, 1), bar);
  });
  ctx.fillStyle = "rgba(106, 160, 255, 0.45)";  // the current frame, bars still visible
  ctx.fillRect(current * step, 0, Math.max(step, 2), h);
  drawTicks(ctx, n, step, h);
}

export function tickEvery(frames, width, minGap = 70) {
  // a round frame interval (1, 2, 5 x 10^k) whose labels are at least minGap px apart
  if (!(width > 0) || !(frames > 0)) return Math.max(frames, 1);
  for (let k = 1; k < frames * 10; k *= 10) {
    for (const m of [1, 2, 5]) if ((m * k * width) / frames >= minGap) return m * k;
  }
  return Math.max(frames, 1);
}

function drawTicks(ctx, n, step, h) {
  // frame numbers along the timeline
  const every = tickEvery(n, step * n);
  ctx.font = "10px system-ui, sans-serif";
  ctx.fillStyle = "#aab";
  ctx.strokeStyle = "#556";
  ctx.lineWidth = 1;
  for (let f = 0; f < n; f += every) {
    const x = Math.round(f * step) + 0.5;
    ctx.beginPath();
    ctx.moveTo(x, 0);
    ctx.lineTo(x, 5);
    ctx.stroke();
    ctx.fillText(String(f), x + 2, 11);
  }
}
