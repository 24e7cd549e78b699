"""Deprecated: `smana.common.ply` is now `smana.common.ply_files` (this name goes in the next
release)."""

from smana.common.moved import moved

moved(__name__, "smana.common.ply_files")
