// Tile layouts that fill the window. "grid": the number of columns that makes the
// tiles largest for the frames' aspect ratio, the 3D view spanning whatever cells the
// last row leaves, so no cell is empty. "focus": one large view and the others as
// thumbnails in a column over its right edge, always in view order (the DOM never
// moves), so a thumbnail keeps its place.

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

export function applyLayout(container, tiles, layout, focus, aspect) {
  // tiles: the view tiles in view order, then the 3D view's tile (last)
  const rect = container.getBoundingClientRect();
  const style = container.style;
  tiles.forEach((tile) => {
    for (const key of ["gridColumn", "gridRow", "order", "position", "top", "right", "width", "height"]) tile.style[key] = "";
  });
  if (layout === "focus") {
    // the large view takes the whole area, the others are insets over its right edge, small
    // enough that its footage keeps 80 % of a 1280x720 window
    const others = tiles.length - 1;
    const h = Math.max(1, Math.floor(Math.min((rect.height - 8) / (others + 5), (rect.width - 8) / 6 / aspect)));
    style.gridTemplateColumns = "minmax(0, 1fr)";
    style.gridTemplateRows = "minmax(0, 1fr)";
    let k = 0;
    tiles.forEach((tile, i) => {
      if (i === focus) return;
      Object.assign(tile.style, { position: "absolute", right: "6px", top: `${6 + k++ * (h + 4)}px`,
        width: `${Math.floor(h * aspect)}px`, height: `${h}px` });
    });
    return { thumb: h };
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
