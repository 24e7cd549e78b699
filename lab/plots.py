"""Deprecated: `smana.lab.plots` is now `smana.lab.paper_figures` (this name goes in the next
release)."""

from smana.common.moved import moved

moved(__name__, "smana.lab.paper_figures")
