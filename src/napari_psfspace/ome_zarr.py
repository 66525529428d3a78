"""Reading a z-stack and its voxel size from an OME-Zarr (OME-NGFF 0.4 or 0.5) image.

The array is the first (full-resolution) dataset of the first multiscale; the voxel
size is the product of the multiscale's and the dataset's ``scale`` transforms, in the
axes' units. Axes ``t`` and ``c`` of length 1 are dropped; longer ones are refused (a
z-stack of one channel is expected).

The metadata are read with ``zarr`` alone: the ecosystem's OME-Zarr reader (``ome-zarr``)
pins a pydantic that napari-psf-analysis, the benches' reference, cannot share.
"""

from __future__ import annotations

import os

import numpy as np

#: NGFF length units in micrometres.
UNITS_UM = {"micrometer": 1.0, "nanometer": 1e-3, "millimeter": 1e3, "angstrom": 1e-4,
            "meter": 1e6, "centimeter": 1e4}


def is_ome_zarr(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder holding Zarr group metadata (v2 or v3)."""
    p = os.fspath(path)
    return os.path.isdir(p) and any(os.path.exists(os.path.join(p, f))
                                    for f in (".zattrs", "zarr.json"))


def _multiscale(attrs: dict, name: str) -> dict:
    ms = attrs.get("multiscales") or (attrs.get("ome") or {}).get("multiscales")
    if not ms:
        raise ValueError(f"{name!r} is a Zarr group without OME-NGFF multiscales metadata; "
                         "expected an OME-Zarr image")
    return ms[0]


def _scale(transforms, n: int) -> np.ndarray:
    out = np.ones(n)
    for t in transforms or []:
        if t.get("type") == "scale" and len(t.get("scale", [])) == n:
            out = out * np.asarray(t["scale"], float)
    return out


def read_ome_zarr(path: str | os.PathLike):
    """The z-stack of an OME-Zarr image and its sampling.

    Returns
    -------
    data : ndarray of shape (Z, Y, X)
    pixel_size, z_spacing : float or None
        µm, from the scale transforms and the axes' units (None where the unit is not a
        length or the axis is missing).
    axes : str
        The axes kept, e.g. "ZYX".
    """
    try:
        import zarr
    except ImportError:
        raise ValueError("reading OME-Zarr needs the `zarr` package: pip install zarr") from None
    name = os.fspath(path)
    try:
        root = zarr.open_group(name, mode="r")
    except Exception as exc:  # zarr raises several kinds on a damaged store
        raise ValueError(f"{name!r} is not a readable Zarr group ({exc})") from exc
    m = _multiscale(dict(root.attrs), name)
    ds = m["datasets"][0]
    arr = root[ds["path"]]
    # NGFF 0.3 and before name no axes: the last ones of t, c, z, y, x
    axes = m.get("axes") or [{"name": a} for a in "tczyx"[-arr.ndim:]]
    names = [(a["name"] if isinstance(a, dict) else str(a)).lower() for a in axes]
    units = [a.get("unit") if isinstance(a, dict) else None for a in axes]
    if len(names) != arr.ndim:
        raise ValueError(f"{name!r}: {len(names)} axes named for an array of {arr.ndim} "
                         "dimensions")
    scale = _scale(m.get("coordinateTransformations"), arr.ndim) * _scale(
        ds.get("coordinateTransformations"), arr.ndim)
    index = []
    for ax, size in zip(names, arr.shape, strict=True):
        if ax in ("t", "c") and size != 1:
            raise ValueError(f"{name!r} has {size} along axis {ax!r}; expected one "
                             "channel at one time point (a z-stack Z, Y, X)")
        index.append(0 if ax in ("t", "c") else slice(None))
    kept = [i for i, ax in enumerate(names) if ax not in ("t", "c")]
    data = np.asarray(arr[tuple(index)])

    def length(axis: str) -> float | None:
        if axis not in names:
            return None
        i = names.index(axis)
        factor = UNITS_UM.get(units[i] or "micrometer")
        return float(scale[i] * factor) if factor else None

    return data, length("x"), length("z"), "".join(names[i].upper() for i in kept)


__all__ = ["UNITS_UM", "is_ome_zarr", "read_ome_zarr"]
