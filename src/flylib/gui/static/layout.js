// Tile layouts that fill the window. "grid": the number of columns that makes the
// tiles largest for the frames' aspect ratio, the 3D view spanning whatever cells the
// last row leaves, so no cell is empty. "focus": one large view on top, the others as
// thumbnails in one row below, always in view order (CSS order, the DOM never moves),
// so a thumbnail keeps its place and its zoom.

export function bestGrid(count, width, height, aspect) {
  // columns x rows for `count` tiles of width/height ratio `aspect` in width x height
  let best = { cols: 1, rows: count, size: 0 };
  for (let cols = 1; cols <= count; cols++) {
    const rows = Math.ceil(count / cols);
    const tileW = Math.min(width / cols, (height / rows) * aspect);
    if (tileW > best.size + 1e-6) best = { cols, rows, size: tileW };
  }
  return best;
}

export function applyLayout(container, tiles, layout, focus, aspect) {
  // tiles: the view tiles in view order, then the 3D view's tile (last)
  const rect = container.getBoundingClientRect();
  const style = container.style;
  tiles.forEach((tile) => { tile.style.gridColumn = ""; tile.style.gridRow = ""; tile.style.order = ""; });
  if (layout === "focus") {
    const others = tiles.length - 1;
    style.gridTemplateColumns = `repeat(${others}, minmax(0, 1fr))`;
    style.gridTemplateRows = "minmax(0, 4fr) minmax(0, 1fr)";
    tiles.forEach((tile, i) => {
      if (i === focus) {
        tile.style.gridColumn = "1 / -1";
        tile.style.gridRow = "1";
        tile.style.order = "-1";
      } else {
        tile.style.order = String(i);
      }
    });
    return { cols: others, rows: 2 };
  }
  const views = tiles.length - 1;
  const grid = bestGrid(tiles.length, rect.width, rect.height, aspect);
  // seven views + 3D in cols x rows: the 3D view takes the cells the views leave
  const cells = grid.cols * grid.rows;
  style.gridTemplateColumns = `repeat(${grid.cols}, minmax(0, 1fr))`;
  style.gridTemplateRows = `repeat(${grid.rows}, minmax(0, 1fr))`;
  const spare = cells - views;
  tiles[views].style.gridColumn = `span ${Math.max(1, Math.min(spare, grid.cols))}`;
  return grid;
}
