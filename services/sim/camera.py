"""The semantic RGB-D camera: TinyRenderer (CPU) images turned into a labelled point cloud.

One `getCameraImage` call gives the RGB image, the depth buffer and the segmentation mask (body
ids). Depth is linearised to metres along the optical axis and unprojected through the pinhole
model; a pixel's class is its body's class, except on the ground height field, whose class is
looked up in the world's ground raster at the pixel's (x, y). Its parameters are `[sim.camera]`
(`CameraConfig`); the default follows the paper: 640 x 640 pixels, 57 degree field of view.

Frames: the sensor frame follows REP-103 (x forward along the optical axis, y left, z up); the
OpenGL camera frame TinyRenderer uses (x right, y up, looking down -z) only appears inside
`view_matrix`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pybullet as p

from smana.common.config.sim import CameraConfig

from .scene import BulletScene
from .worlds import Raster

# OpenGL camera axes (right, up, backward) expressed in the REP-103 sensor frame
_SENSOR_FROM_GL = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def view_matrix(world_from_sensor: np.ndarray) -> list[float]:
    """OpenGL view matrix (column-major, as PyBullet wants it) for a REP-103 sensor pose."""
    world_from_gl = np.eye(4)
    world_from_gl[:3, :3] = world_from_sensor[:3, :3] @ _SENSOR_FROM_GL
    world_from_gl[:3, 3] = world_from_sensor[:3, 3]
    return np.linalg.inv(world_from_gl).T.ravel().tolist()


def linearise_depth(zbuffer: np.ndarray, near: float, far: float) -> np.ndarray:
    """OpenGL depth buffer values in [0, 1] -> distance along the optical axis, metres."""
    z = np.asarray(zbuffer, np.float64)
    return far * near / (far - (far - near) * z)


def unproject(depth_m: np.ndarray, focal_px: float, rows=None, cols=None) -> np.ndarray:
    """Depth -> points in the sensor frame (pixel centres at +0.5). With `rows`/`cols`, only
    those pixels of the (H, W) depth image, as (N, 3); otherwise the whole image as (H, W, 3)."""
    h, w = depth_m.shape
    if rows is None:
        rows, cols = (a.ravel() for a in np.mgrid[0:h, 0:w])
        shape = (h, w, 3)
    else:
        shape = (len(rows), 3)
    d = depth_m[rows, cols].astype(np.float32)
    pts = np.empty((len(d), 3), np.float32)
    pts[:, 0] = d
    pts[:, 1] = -((cols + 0.5 - w / 2) / focal_px) * d  # pixel columns grow to the right
    pts[:, 2] = -((rows + 0.5 - h / 2) / focal_px) * d  # pixel rows grow downwards
    return pts.reshape(shape)


class RenderedImages(NamedTuple):
    """What TinyRenderer gives, as the kernel reads it."""

    zbuf: np.ndarray  # f4 (H, W): OpenGL depth buffer in [0, 1]
    seg: np.ndarray  # i4 (H, W): body id per pixel, < 0 for background
    rgba: np.ndarray  # u1 (H, W, >= 3)


class LabelledImages(NamedTuple):
    """The kernel's outputs (`label_pixels`)."""

    depth_m: np.ndarray  # f4 (H, W)
    labels: np.ndarray  # i4 (H, W)
    rgb: np.ndarray  # u1 (H, W, 3)


class Pinhole(NamedTuple):
    near: float
    far: float
    focal_px: float
    max_range_m: float


class GroundLookup(NamedTuple):
    """The ground raster's classes and placement (`worlds.Raster`)."""

    classes: np.ndarray  # i4 (nx, ny)
    x0: float
    y0: float
    resolution_m: float


def label_pixels(
    zbuf: np.ndarray,
    seg: np.ndarray,
    rgba: np.ndarray,
    *,
    near: float,
    far: float,
    focal_px: float,
    max_range_m: float,
    world_from_sensor: np.ndarray,
    label_lut: np.ndarray,
    ground: Raster,
    colour_lut: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth buffer and segmentation mask -> (depth_m f4[H,W], labels i4[H,W], rgb u1[H,W,3]).

    `labels` is the class id of each pixel, -1 where there is no point (background, beyond
    `max_range_m`, or a body whose `label_lut` entry is DROP or MEMBER); `label_lut[body] ==
    GROUND` means "class of the ground raster at the pixel's world (x, y)". Ground pixels are
    coloured by class. A MEMBER body (a fleet's robot: seen, not mapped) keeps its depth.
    """
    zbuf = np.ascontiguousarray(zbuf, np.float32)
    seg = np.ascontiguousarray(seg, np.int32)
    rgba = np.ascontiguousarray(rgba, np.uint8)
    h, w = zbuf.shape
    if seg.shape != (h, w) or rgba.shape[:2] != (h, w) or rgba.shape[2] < 3:
        raise ValueError(f"image shapes disagree: {zbuf.shape}, {seg.shape}, {rgba.shape}")
    if not 0 < near < far or not focal_px > 0 or not max_range_m > 0:
        raise ValueError("need 0 < near < far, focal_px > 0 and max_range_m > 0")
    m = np.asarray(world_from_sensor, np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError("world_from_sensor must be a finite 4x4 matrix")
    lut = np.ascontiguousarray(label_lut, np.int32)
    classes = np.ascontiguousarray(ground.data, np.int32)
    if classes.size and (classes.min() < 0 or classes.max() >= len(colour_lut)):
        raise ValueError("ground raster holds ids outside the colour table")
    out = LabelledImages(
        np.empty((h, w), np.float32), np.empty((h, w), np.int32), np.empty((h, w, 3), np.uint8)
    )
    from .camera_kernel import label_pixels_kernel  # numba: imported on the first frame

    label_pixels_kernel(
        RenderedImages(zbuf, seg, rgba),
        Pinhole(float(near), float(far), float(focal_px), float(max_range_m)),
        np.ascontiguousarray(m),
        lut,
        GroundLookup(
            classes,
            float(ground.origin_xy[0]),
            float(ground.origin_xy[1]),
            float(ground.resolution_m),
        ),
        np.ascontiguousarray(colour_lut, np.float64),
        out,
    )
    return out.depth_m, out.labels, out.rgb


@dataclass
class CameraCapture:
    """One rendered frame, before any degradation. `labels` is -1 where no point exists."""

    rgb: np.ndarray  # u1[H, W, 3]
    depth_m: np.ndarray  # f4[H, W], +inf where there is no point
    labels: np.ndarray  # i4[H, W] class ids, -1 where there is no point
    world_from_sensor: np.ndarray  # 4x4 true sensor pose used to render
    focal_px: float
    member_px: int = 0  # pixels on the bodies `capture` was asked to count (other robots)

    @property
    def valid(self) -> np.ndarray:
        return self.labels >= 0

    def points_sensor(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Points (N, 3) of the given pixels, sensor frame."""
        return unproject(self.depth_m, self.focal_px, rows, cols)


class SemanticCamera:
    def __init__(self, scene: BulletScene, config: CameraConfig | None = None):
        self.scene = scene
        self.config = s = config or CameraConfig()
        # the far plane sits a little past the range, so that every in-range pixel is rendered
        self._far = s.max_range_m * 1.05
        self._proj = p.computeProjectionMatrixFOV(
            s.fov_deg, s.width / s.height, s.near_m, self._far
        )

    def capture(
        self,
        world_from_sensor: np.ndarray,
        timings: dict | None = None,
        count_bodies: np.ndarray | None = None,
    ) -> CameraCapture:
        """Render from a sensor pose (4x4, world frame) and label every pixel. With
        `count_bodies`, the pixels showing those bodies are counted (`member_px`).

        A pose that puts a ground vertex exactly in the camera's plane (e.g. a camera looking
        level, exactly above a grid vertex) makes TinyRenderer rasterise a degenerate triangle
        over the whole screen, 20x slower; poses a moving robot takes never hit it exactly."""
        s = self.config
        t0 = time.perf_counter()
        _, _, rgba, zbuf, seg = p.getCameraImage(
            s.width,
            s.height,
            view_matrix(world_from_sensor),
            self._proj,
            renderer=p.ER_TINY_RENDERER,
            shadow=0,
            physicsClientId=self.scene.client,
        )
        t1 = time.perf_counter()
        seg = np.asarray(seg, np.int32).reshape(s.height, s.width)
        member_px = 0
        if count_bodies is not None and len(count_bodies):
            member_px = int(np.isin(seg, count_bodies).sum())
        depth, labels, rgb = label_pixels(
            np.asarray(zbuf, np.float32).reshape(s.height, s.width),
            seg,
            np.asarray(rgba, np.uint8).reshape(s.height, s.width, 4),
            near=s.near_m,
            far=self._far,
            focal_px=s.focal_px,
            max_range_m=s.max_range_m,
            world_from_sensor=world_from_sensor,
            label_lut=self.scene.label_lut,
            ground=self.scene.world.ground.class_raster(),
            colour_lut=self.scene.world.classes.colour_lut,
        )
        if timings is not None:
            timings["render_ms"] = 1e3 * (t1 - t0)
            timings["label_ms"] = 1e3 * (time.perf_counter() - t1)
        return CameraCapture(
            rgb, depth, labels, np.array(world_from_sensor, float), s.focal_px, member_px
        )
