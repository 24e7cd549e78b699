"""A top-down picture of a world: the class seen from above, hill-shaded so objects read as
raised (`smana world preview`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .world import World


def top_down_image(world: World, pixels: int = 768) -> np.ndarray:
    """RGB u1[H, W, 3] of the classes (x to the right, y up), about `pixels` wide."""
    top_c, top_h = world.top_class(), world.top_height()
    rgb = world.classes.colour_lut[top_c.data].astype(np.float64)
    gx, gy = np.gradient(top_h.data, top_h.resolution_m)
    # hill shading with light from the north-west
    shade = np.clip(1.0 - 0.35 * (gx - gy) / np.sqrt(1 + gx * gx + gy * gy), 0.55, 1.25)
    rgb = np.clip(rgb * shade[..., None], 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(np.transpose(rgb, (1, 0, 2))[::-1])
    scale = max(1, pixels // max(img.shape[:2]))
    return np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
