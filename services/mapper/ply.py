"""Deprecated: `smana.services.mapper.ply` is now `smana.services.mapper.voxel_ply` (this name goes
in the next release)."""

from smana.common.moved import moved

moved(__name__, "smana.services.mapper.voxel_ply")
