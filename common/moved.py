"""Old import paths kept for one release after a module was renamed: the old module is a shim of
two lines that calls `moved`, which warns (DeprecationWarning) and puts the new module in its
place, so `from smana.<old> import name` gets the very object `smana.<new>` holds."""

from __future__ import annotations

import importlib
import sys
import warnings


def moved(old: str, new: str) -> None:
    """Make module `old` (a shim being imported) the module `new`, with a DeprecationWarning
    that names the new path."""
    warnings.warn(
        f"{old} is now {new}; the old name goes in the next release",
        DeprecationWarning,
        stacklevel=3,
    )
    sys.modules[old] = importlib.import_module(new)
