"""Deprecated: `smana.services.sim.ply` is now `smana.services.sim.labelled_ply` (this name goes in
the next release)."""

from smana.common.moved import moved

moved(__name__, "smana.services.sim.labelled_ply")
