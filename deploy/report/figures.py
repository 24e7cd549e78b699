"""Deprecated: `smana.deploy.report.figures` is now `smana.deploy.report.run_plots` (this name goes
in the next release)."""

from smana.common.moved import moved

moved(__name__, "smana.deploy.report.run_plots")
