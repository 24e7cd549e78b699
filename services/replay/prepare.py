"""Turn a dataset scan into what the mapper integrates: table labels, world frame, in range.

Dataset ids become class-table ids (`maps_from`), points of ignored classes (sky, void) and
points outside [min_range_m, max_range_m] from the sensor are dropped, as are non-finite points,
and the rest is moved to the world frame. Every drop is counted, so a replay can say how much of
the data it published.

A scan without labels (`Scan.labels` None, `--label-field none`) is labelled after the pose is
applied, by the geometric labeller (common/geometric.py) on the points kept: ids of the
`geometric` table, judged in the world frame where z is up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from smana.common.classes import ClassTable
from smana.common.geometric import TABLE as GEOMETRIC_TABLE
from smana.common.geometric import GeometricLabeller
from smana.common.messages import matrix_to_quat

from .readers.base import Scan


@dataclass
class PreparedCloud:
    points: np.ndarray  # f4[N, 3], world frame
    labels: np.ndarray  # u2[N], class-table ids
    confidences: np.ndarray  # f4[N]
    sensor_position: np.ndarray  # f8[3]
    sensor_orientation_xyzw: np.ndarray  # f8[4]
    n_in: int = 0
    n_nonfinite: int = 0
    n_out_of_range: int = 0
    n_ignored: int = 0
    n_unclaimed: int = 0  # dataset ids no class claims (kept, as unknown)
    n_out: int = 0  # points kept (also when the arrays themselves are not kept)


def prepare_scan(
    scan: Scan,
    table: ClassTable,
    max_range_m: float,
    min_range_m: float = 0.0,
    labeller: GeometricLabeller | None = None,
) -> PreparedCloud:
    """Filter and transform one scan (see the module docstring). Raises ValueError on bad input,
    and on a scan without labels when there is no `labeller` or `table` is not `geometric`."""
    if not (0 <= min_range_m < max_range_m):
        raise ValueError(f"need 0 <= min_range_m < max_range_m, got {min_range_m}, {max_range_m}")
    pts = np.asarray(scan.points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"scan {scan.name}: points have shape {pts.shape}, expected (N, 3)")
    unlabelled = scan.labels is None
    if unlabelled and (labeller is None or table.name != GEOMETRIC_TABLE):
        raise ValueError(
            f"scan {scan.name} has no labels: it needs the geometric labeller and the "
            f"{GEOMETRIC_TABLE!r} class table (got {table.name!r})"
        )
    if not unlabelled and scan.labels.shape != (pts.shape[0],):
        raise ValueError(f"scan {scan.name}: {scan.labels.size} labels for {pts.shape[0]} points")
    pose = np.asarray(scan.pose, np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"scan {scan.name}: pose must be a finite 4x4 matrix")
    conf = scan.confidences
    conf = np.ones(pts.shape[0], np.float32) if conf is None else np.asarray(conf, np.float32)

    if unlabelled:  # labelled below, in the world frame; no class is ignored
        labels, n_unclaimed = None, 0
    else:
        labels, n_unclaimed = table.map_dataset_labels(scan.labels)
    finite = np.isfinite(pts).all(axis=1) & np.isfinite(conf)
    r2 = np.einsum("ij,ij->i", pts, pts, dtype=np.float64)
    # The sensor's "no return" points sit at the origin: min_range_m > 0 drops them as well.
    in_range = (r2 <= max_range_m**2) & (r2 >= min_range_m**2)
    if unlabelled:
        kept_class = np.ones(pts.shape[0], bool)
    else:
        kept_class = ~table.ignored_lut[np.minimum(labels, table.size - 1)]
    keep = finite & in_range & kept_class
    world = (pts[keep].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
    kept_labels = labeller.label(world, pose[:3, 3]) if unlabelled else labels[keep]
    return PreparedCloud(
        points=world,
        labels=kept_labels,
        confidences=np.clip(conf[keep], 0.0, 1.0),
        sensor_position=pose[:3, 3].copy(),
        sensor_orientation_xyzw=matrix_to_quat(pose[:3, :3]),
        n_in=int(pts.shape[0]),
        n_nonfinite=int((~finite).sum()),
        n_out_of_range=int((finite & ~in_range).sum()),
        n_ignored=int((finite & in_range & ~kept_class).sum()),
        n_unclaimed=n_unclaimed,
        n_out=int(keep.sum()),
    )
