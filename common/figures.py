"""Deprecated: `smana.common.figures` is now `smana.common.plotting` (this name goes in the next
release)."""

from smana.common.moved import moved

moved(__name__, "smana.common.plotting")
