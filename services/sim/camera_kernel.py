"""The camera's pixel-labelling kernel, behind camera.py's checked `label_pixels`, which imports
this module on the first frame: numba stays out of the sim service's imports (a quarter of a
second of CPU) until it renders."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def label_pixels_kernel(images, pinhole, world_from_sensor, lut, ground, colour_lut, out):
    """`label_pixels` on checked arrays; every field is read into a local before the loops."""
    zbuf, seg, rgba = images
    near, far, focal, max_range = pinhole
    ground_classes, g_x0, g_y0, g_res = ground
    depth_out, labels_out, rgb_out = out
    pose = world_from_sensor  # rotation in [:3, :3], translation in [:3, 3]
    h, w = zbuf.shape
    nx, ny = ground_classes.shape
    n_lut = lut.shape[0]
    max_r2 = max_range * max_range
    for r in range(h):
        v = (r + 0.5 - h / 2) / focal
        for c in range(w):
            for k in range(3):
                rgb_out[r, c, k] = rgba[r, c, k]
            depth_out[r, c] = np.inf
            labels_out[r, c] = -1
            body = seg[r, c]
            z = zbuf[r, c]
            if body < 0 or z >= 1.0:
                continue
            d = far * near / (far - (far - near) * z)
            u = (c + 0.5 - w / 2) / focal
            x, y, zz = d, -u * d, -v * d
            if x * x + y * y + zz * zz > max_r2:
                continue
            label = lut[body] if body < n_lut else -1
            if label == -2:  # the ground height field: class from the raster under the point
                wx = pose[0, 0] * x + pose[0, 1] * y + pose[0, 2] * zz + pose[0, 3]
                wy = pose[1, 0] * x + pose[1, 1] * y + pose[1, 2] * zz + pose[1, 3]
                ix = min(max(int(np.floor((wx - g_x0) / g_res + 0.5)), 0), nx - 1)
                iy = min(max(int(np.floor((wy - g_y0) / g_res + 0.5)), 0), ny - 1)
                label = ground_classes[ix, iy]
                # the height field renders white, so its grey level is the lighting
                shade = (rgba[r, c, 0] + rgba[r, c, 1] + rgba[r, c, 2]) / (3.0 * 255.0)
                for k in range(3):
                    rgb_out[r, c, k] = min(colour_lut[label, k] * shade, 255.0)
            if label == -3:  # a fleet's robot (MEMBER): in the depth image, not in the cloud
                depth_out[r, c] = d
                continue
            if label < 0:
                continue
            depth_out[r, c] = d
            labels_out[r, c] = label
