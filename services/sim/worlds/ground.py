"""The ground of a world: a height field with a class per vertex (`GroundModel`), and `Raster`,
the 2D grid aligned with it that every top-down query answers in."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import WorldError


@dataclass
class Raster:
    """A 2D grid aligned with the ground's vertices: cell (i, j) is centred at
    origin_xy + (i, j) * resolution_m; `data` is indexed [ix, iy]."""

    origin_xy: tuple[float, float]
    resolution_m: float
    data: np.ndarray

    def index_of(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Nearest cell indices, clipped to the grid."""
        nx, ny = self.data.shape[:2]
        ix = np.rint((np.asarray(x) - self.origin_xy[0]) / self.resolution_m).astype(np.int64)
        iy = np.rint((np.asarray(y) - self.origin_xy[1]) / self.resolution_m).astype(np.int64)
        return np.clip(ix, 0, nx - 1), np.clip(iy, 0, ny - 1)

    def at(self, x, y) -> np.ndarray:
        return self.data[self.index_of(x, y)]

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        nx, ny = self.data.shape[:2]
        xs = self.origin_xy[0] + np.arange(nx) * self.resolution_m
        ys = self.origin_xy[1] + np.arange(ny) * self.resolution_m
        return xs, ys


@dataclass
class GroundModel:
    """Heights and ground classes at the vertices of a regular grid (x index first).

    `height_at` interpolates exactly as Bullet's height field triangulates each cell (the diagonal
    joins vertex (i+1, j) to (i, j+1)), so points on the simulated ground agree with it.
    """

    origin_xy: tuple[float, float]
    resolution_m: float
    heights: np.ndarray  # f8[nx, ny]
    classes: np.ndarray  # u2[nx, ny]

    def __post_init__(self):
        if self.heights.shape != self.classes.shape or self.heights.ndim != 2:
            raise WorldError("ground heights and classes must be 2D arrays of one shape")
        if min(self.heights.shape) < 2:
            raise WorldError("ground grid needs at least 2 x 2 vertices")

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    @property
    def extent(self) -> tuple[float, float, float, float]:
        nx, ny = self.shape
        x0, y0 = self.origin_xy
        return x0, y0, x0 + (nx - 1) * self.resolution_m, y0 + (ny - 1) * self.resolution_m

    def height_at(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        nx, ny = self.shape
        fx = np.clip((x - self.origin_xy[0]) / self.resolution_m, 0, nx - 1)
        fy = np.clip((y - self.origin_xy[1]) / self.resolution_m, 0, ny - 1)
        i = np.minimum(fx.astype(np.int64), nx - 2)
        j = np.minimum(fy.astype(np.int64), ny - 2)
        s, t = fx - i, fy - j
        h = self.heights
        h00, h10, h01, h11 = h[i, j], h[i + 1, j], h[i, j + 1], h[i + 1, j + 1]
        lower = h00 + s * (h10 - h00) + t * (h01 - h00)
        upper = h11 + (1 - s) * (h01 - h11) + (1 - t) * (h10 - h11)
        return np.where(s + t <= 1.0, lower, upper)

    def class_at(self, x, y) -> np.ndarray:
        return self.class_raster().at(x, y)

    def class_raster(self) -> Raster:
        return Raster(self.origin_xy, self.resolution_m, self.classes)

    def height_raster(self) -> Raster:
        return Raster(self.origin_xy, self.resolution_m, self.heights)
