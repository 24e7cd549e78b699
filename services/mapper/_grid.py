"""Deprecated: the block grid is `smana.services.mapper.block_grid` (this name goes in the next
release)."""

from smana.common.moved import moved

moved(__name__, "smana.services.mapper.block_grid")
