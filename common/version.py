"""The installed smana's version, for what a run or a map records about who made it."""

from functools import cache
from importlib.metadata import PackageNotFoundError, version


@cache
def smana_version() -> str:
    """The version in the installed package's metadata ("unknown" in a bare checkout)."""
    try:
        return version("smana")
    except PackageNotFoundError:
        return "unknown"
