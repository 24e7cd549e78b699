"""Deprecated: `smana.common.schema` is now `smana.common.message_schema` (this name goes in the
next release)."""

from smana.common.moved import moved

moved(__name__, "smana.common.message_schema")
