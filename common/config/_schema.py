"""Deprecated: the typed-config mechanism is `smana.common.config.section` (this name goes in the
next release)."""

from smana.common.moved import moved

moved(__name__, "smana.common.config.section")
