// Tile layouts that fill the window. "grid": the number of columns that makes the
// tiles largest for the frames' aspect ratio, the 3D view spanning whatever cells the
// last row leaves, so no cell is empty. "focus": one large view and the others as
// thumbnails in a column beside it or a row below it, whichever leaves the large
// frame the most room, always in view order (CSS order, the DOM never moves), so a
// thumbnail keeps its place and its zoom.

export function bestGrid(count, width, height, aspect, gap = 0) {
  // columns x rows for `count` tiles of width/height ratio `aspect` in width x height
  let best = { cols: 1, rows: count, size: 0 };
  for (let cols = 1; cols <= count; cols++) {
    const rows = Math.ceil(count / cols);
    const tileW = Math.min((width - gap * (cols - 1)) / cols, ((height - gap * (rows - 1)) / rows) * aspect);
    if (tileW > best.size + 1e-6) best = { cols, rows, size: tileW };
  }
  return best;
}

function frameArea(width, height, aspect) {
  const w = Math.max(0, Math.min(width, height * aspect));
  return (w * w) / aspect;
}

export function bestFocus(others, width, height, aspect, gap = 4) {
  // where the thumbnails go: "side" (1 or 2 columns) or "below" (one row), and their size
  let best = null;
  for (const columns of [1, 2]) {
    const perColumn = Math.ceil(others / columns);
    const thumbH = (height - gap * (perColumn - 1)) / perColumn;
    const thumbW = thumbH * aspect;
    const area = frameArea(width - columns * (thumbW + gap), height, aspect);
    if (!best || area > best.area) best = { where: "side", columns, thumb: thumbW, area };
  }
  const thumbW = (width - gap * (others - 1)) / others;
  const thumbH = thumbW / aspect;
  const area = frameArea(width, height - thumbH - gap, aspect);
  if (area > best.area) best = { where: "below", columns: others, thumb: thumbH, area };
  return best;
}

export function applyLayout(container, tiles, layout, focus, aspect) {
  // tiles: the view tiles in view order, then the 3D view's tile (last)
  const rect = container.getBoundingClientRect();
  const style = container.style;
  tiles.forEach((tile) => { tile.style.gridColumn = ""; tile.style.gridRow = ""; tile.style.order = ""; });
  if (layout === "focus") {
    const others = tiles.length - 1;
    const plan = bestFocus(others, rect.width - 8, rect.height - 8, aspect);
    if (plan.where === "side") {
      const rows = Math.ceil(others / plan.columns);
      style.gridTemplateColumns = `minmax(0, 1fr) repeat(${plan.columns}, ${Math.floor(plan.thumb)}px)`;
      style.gridTemplateRows = `repeat(${rows}, minmax(0, 1fr))`;
    } else {
      style.gridTemplateColumns = `repeat(${others}, minmax(0, 1fr))`;
      style.gridTemplateRows = `minmax(0, 1fr) ${Math.floor(plan.thumb)}px`;
    }
    tiles.forEach((tile, i) => {
      if (i === focus) {
        tile.style.gridColumn = plan.where === "side" ? "1" : "1 / -1";
        tile.style.gridRow = plan.where === "side" ? "1 / -1" : "1";
        tile.style.order = "-1";
      } else {
        tile.style.order = String(i);
      }
    });
    return plan;
  }
  const views = tiles.length - 1;
  const grid = bestGrid(tiles.length, rect.width - 8, rect.height - 8, aspect, 4);
  // seven views + 3D in cols x rows: the 3D view takes the cells the views leave; each
  // cell has the frames' shape (the grid centred), so a frame fills its tile
  const cells = grid.cols * grid.rows;
  const tileW = Math.max(1, Math.floor(grid.size));
  style.gridTemplateColumns = `repeat(${grid.cols}, ${tileW}px)`;
  style.gridTemplateRows = `repeat(${grid.rows}, ${Math.max(1, Math.floor(tileW / aspect))}px)`;
  const spare = cells - views;
  tiles[views].style.gridColumn = `span ${Math.max(1, Math.min(spare, grid.cols))}`;
  return grid;
}
