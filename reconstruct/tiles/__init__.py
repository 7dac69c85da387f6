"""Full frames in tiles: layout (:mod:`.geometry`), blending (:mod:`.blend`), memory (:mod:`.memory`),
the tile's capture (:mod:`.crop`), the tiled run (:mod:`.run`) and frames/tiles on Dask (:mod:`.distributed`)."""

from .blend import TileBlender, axis_weight, tile_weight
from .geometry import MIN_TILE, TILE_ALIGN, Tile, TileLayout, default_margin, plan_tiles, split_axis
from .memory import estimate_bytes, memory_budget, tile_for_budget
from .run import choose_layout, reconstruct_tiled

__all__ = ["MIN_TILE", "TILE_ALIGN", "Tile", "TileBlender", "TileLayout", "axis_weight", "choose_layout",
           "default_margin", "estimate_bytes", "memory_budget", "plan_tiles", "reconstruct_tiled", "split_axis",
           "tile_for_budget", "tile_weight"]
