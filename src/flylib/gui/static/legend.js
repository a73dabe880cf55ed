// The legend (every mark the views draw, and the limb colours) and point-name labels
// drawn beside a hovered or selected point. DOM built with text nodes only.

export function buildLegend(container, meta) {
  const title = document.createElement("h2");
  title.textContent = "Legend";
  const list = document.createElement("ul");
  list.className = "legend";
  const marks = [
    ["dot", "filled dot: 2D used by the triangulation"],
    ["hollow", "hollow dot: 2D the robust triangulation dropped"],
    ["cross", "cross, dashed bones: the 3D reprojected (ghost)"],
    ["edited", "white ring: your edit"],
    ["fixed", "yellow square: fixed (always used; f)"],
    ["suspect", "red ring: suspect point"],
    ["selected", "blue ring: selected point"],
    ["invisible", "white square: marked invisible (shows the ghost)"],
  ];
  for (const [kind, text] of marks) {
    const li = document.createElement("li");
    const swatch = document.createElement("span");
    swatch.className = `mark ${kind}`;
    li.append(swatch, document.createTextNode(text));
    list.appendChild(li);
  }
  // limb colours: points sharing a colour, named by their common prefix
  const groups = new Map();
  meta.points.forEach((name, i) => {
    const color = meta.point_colors[i];
    if (!groups.has(color)) groups.set(color, []);
    groups.get(color).push(name);
  });
  for (const [color, names] of groups) {
    const li = document.createElement("li");
    const swatch = document.createElement("span");
    swatch.className = "mark limb";
    swatch.style.backgroundColor = color;
    li.title = names.join(", ");
    li.append(swatch, document.createTextNode(`${commonPrefix(names)} (${names.length} points)`));
    list.appendChild(li);
  }
  container.replaceChildren(title, list);
}

function commonPrefix(names) {
  let prefix = names[0] || "";
  for (const n of names) while (!n.startsWith(prefix)) prefix = prefix.slice(0, -1);
  prefix = prefix.replace(/[_\d]+$/, "");
  return prefix || names[0];
}

export function drawPointLabel(canvas, xy, text, color) {
  // a name beside canvas position xy, on a dark box so it reads on any footage
  const ctx = canvas.getContext("2d");
  const dpr = window.devicePixelRatio || 1;
  ctx.font = `${12 * dpr}px system-ui, sans-serif`;
  const w = ctx.measureText(text).width + 8 * dpr, h = 16 * dpr;
  let x = xy[0] + 10 * dpr, y = xy[1] - h - 4 * dpr;
  if (x + w > canvas.width) x = xy[0] - w - 10 * dpr;
  if (y < 0) y = xy[1] + 6 * dpr;
  ctx.fillStyle = "rgba(0, 0, 0, 0.75)";
  ctx.fillRect(x, y, w, h);
  ctx.strokeStyle = color;
  ctx.lineWidth = 1 * dpr;
  ctx.strokeRect(x, y, w, h);
  ctx.fillStyle = "#fff";
  ctx.fillText(text, x + 4 * dpr, y + 12 * dpr);
}

export function drawFixedMark(canvas, xy) {
  const ctx = canvas.getContext("2d");
  const dpr = window.devicePixelRatio || 1;
  const r = 6 * dpr;
  ctx.strokeStyle = "#ffd23f";
  ctx.lineWidth = 1.5 * dpr;
  ctx.strokeRect(xy[0] - r, xy[1] - r, 2 * r, 2 * r);
}
