"""A top-down picture of a world: the class seen from above, hill-shaded so objects read as
raised (`smana world preview` draws it, with axes and a legend, through common/plotting.py)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .world import World


def shaded_classes(world: World) -> np.ndarray:
    """RGB u1[nx, ny, 3] indexed [ix, iy] like the world's rasters: each cell's top class in the
    class table's colour, hill-shaded with light from the north-west."""
    top_c, top_h = world.top_class(), world.top_height()
    rgb = world.classes.colour_lut[top_c.data].astype(np.float64)
    gx, gy = np.gradient(top_h.data, top_h.resolution_m)
    shade = np.clip(1.0 - 0.35 * (gx - gy) / np.sqrt(1 + gx * gx + gy * gy), 0.55, 1.25)
    return np.clip(rgb * shade[..., None], 0, 255).astype(np.uint8)
