"""Deprecated: `smana.lab.fuzz` is now `smana.lab.fuzz_messages` (this name goes in the next
release)."""

from smana.common.moved import moved

moved(__name__, "smana.lab.fuzz_messages")
