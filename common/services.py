"""Deprecated: `smana.common.services` is now `smana.common.service_table` (this name goes in the
next release)."""

from smana.common.moved import moved

moved(__name__, "smana.common.service_table")
