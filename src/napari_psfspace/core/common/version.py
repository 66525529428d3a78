"""The package's version, from one source: the installed distribution's metadata
(``pyproject.toml``'s ``version``, through :mod:`importlib.metadata`)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

#: The distribution whose version is read.
DISTRIBUTION = "napari-psfspace"


def package_version() -> str:
    """The installed version; "unknown" when the package runs from a tree that was never
    installed (no metadata to read)."""
    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown"


def software_string() -> str:
    """``"napari-psfspace X.Y.Z"``: what the files and reports record as their writer."""
    return f"{DISTRIBUTION} {package_version()}"


__all__ = ["DISTRIBUTION", "package_version", "software_string"]
