"""Deprecated: `smana.common.service_books` is now `smana.common.service_io` (this name goes in the
next release)."""

from smana.common.moved import moved

moved(__name__, "smana.common.service_io")
