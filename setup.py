"""Packaging: every package under the four top-level folders, found, never listed.

The folders of the design card (`common/`, `services/`, `deploy/`) and the research harness
(`lab/`) are installed under one `smana` namespace (`common/` is `smana.common`, ...), so that
nothing generic lands in site-packages. pyproject.toml's `[tool.setuptools]` table cannot prefix
what it discovers, so the discovery lives here: a new folder (a service, a back-end family, a
data folder such as `common/classes/`) is in the wheel without an edit. Everything else about the
package (metadata, dependencies, package data) is in pyproject.toml.
"""

from setuptools import find_namespace_packages, setup

ROOTS = ("common", "services", "deploy", "lab")


def _packages() -> list[str]:
    found = find_namespace_packages(
        include=[*ROOTS, *(f"{r}.*" for r in ROOTS)], exclude=["*__pycache__*"]
    )
    return sorted(f"smana.{p}" for p in found)


setup(packages=_packages(), package_dir={f"smana.{r}": r for r in ROOTS})
