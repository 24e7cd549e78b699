"""RELLIS-3D layout: `Rellis-3D/0000N/os1_cloud_node_kitti_bin/NNNNNN.bin` and
`os1_cloud_node_semantickitti_label_id/NNNNNN.label`, with `poses.txt` and `calib.txt`.

The files are SemanticKITTI's (see `semantickitti.py`); only folder names differ. A sequence
without `calib.txt` is read with its poses taken as LiDAR poses (Tr = identity).
"""

from __future__ import annotations

from .semantickitti import KittiLayoutReader


class Rellis3dReader(KittiLayoutReader):
    format = "rellis3d"
    default_class_table = "rellis3d"
    cloud_dir = "os1_cloud_node_kitti_bin"
    label_dir = "os1_cloud_node_semantickitti_label_id"
    sequences_dir = "Rellis-3D"
    calib_required = False
