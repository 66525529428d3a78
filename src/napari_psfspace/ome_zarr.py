"""Reading a z-stack and its voxel size from an OME-Zarr (OME-NGFF 0.4 or 0.5) image, and
writing one (NGFF 0.4) a chunk at a time.

The array is the first (full-resolution) dataset of the first multiscale; the voxel
size is the product of the multiscale's and the dataset's ``scale`` transforms, in the
axes' units. Axes ``t`` and ``c`` of length 1 are dropped; longer ones are refused (a
z-stack of one channel is expected).

A written image holds one full-resolution dataset ``0`` with the voxel size as its scale
(µm), chunked by plane ``(1, C, C)`` (a viewer reads the plane it shows). Every chunk is
written whole by Zarr's store (a temporary file renamed into place), so an interrupted
writer leaves only whole chunks, and :func:`missing_chunks` says which are still to be
written.

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


def read_ome_zarr(path: str | os.PathLike, *, lazy: bool = False, complete: bool = True):
    """The z-stack of an OME-Zarr image and its sampling.

    Parameters
    ----------
    path : str or PathLike
    lazy : bool
        Return a dask array on the store, read a chunk at a time when computed.
    complete : bool
        Refuse an image some of whose chunks are missing (Zarr reads each as its fill
        value, which would pass for data); False opens it as it is (to view a partly
        written image).

    Returns
    -------
    data : ndarray or dask.array.Array of shape (Z, Y, X)
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
    try:
        arr = root[ds["path"]]
    except KeyError:
        raise ValueError(f"{name!r} names a dataset {ds['path']!r} it does not hold") from None
    kind = np.dtype(arr.dtype).kind
    if kind not in "uif":
        raise ValueError(f"{name!r} holds {arr.dtype} data; expected intensities (integers "
                         "or floats)")
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
    if complete and arr.nchunks_initialized < arr.nchunks:
        raise ValueError(f"{name!r} is incomplete: {arr.nchunks - arr.nchunks_initialized} of "
                         f"its {arr.nchunks} chunks are missing (Zarr would read them as "
                         f"{arr.fill_value}: a copy cut short, or a writer that skips the "
                         "chunks equal to it); expected a complete image")
    if lazy:
        import dask.array as da

        data = da.from_zarr(arr)[tuple(index)]
    else:
        data = np.asarray(arr[tuple(index)])

    def length(axis: str) -> float | None:
        if axis not in names:
            return None
        i = names.index(axis)
        factor = UNITS_UM.get(units[i] or "micrometer")
        return float(scale[i] * factor) if factor else None

    return data, length("x"), length("z"), "".join(names[i].upper() for i in kept)


def _zarr():
    try:
        import zarr
    except ImportError:
        raise ValueError("writing OME-Zarr needs the `zarr` package: pip install zarr") from None
    return zarr


def create_ome_zarr(path: str | os.PathLike, shape: tuple[int, int, int], *,
                    dtype="float32", voxel_size: tuple[float, float, float] | None = None,
                    chunk: int = 512):
    """An empty OME-Zarr image (NGFF 0.4, Zarr v2) of a z-stack, to be written a chunk at
    a time.

    Parameters
    ----------
    path : str or PathLike
        The image's folder; it must not exist.
    shape : tuple of int (Z, Y, X)
    dtype : dtype
    voxel_size : tuple of float (z, y, x), optional
        µm; written as the dataset's scale (1 where not given, with no unit).
    chunk : int
        Lateral chunk size, pixels; every chunk is one plane's.

    Returns
    -------
    zarr.Array
        The dataset ``0``, filled with 0 where nothing is written.
    """
    zarr = _zarr()
    name = os.fspath(path)
    if os.path.exists(name):
        raise ValueError(f"{name!r} exists; the OME-Zarr output must be a new folder")
    z, h, w = (int(v) for v in shape)
    root = zarr.open_group(name, mode="w-", zarr_format=2)
    arr = root.create_array("0", shape=(z, h, w), dtype=dtype,
                            chunks=(1, min(chunk, h), min(chunk, w)), fill_value=0,
                            chunk_key_encoding={"name": "v2", "separator": "/"},
                            config={"write_empty_chunks": True})
    unit = {} if voxel_size is None else {"unit": "micrometer"}
    scale = [1.0, 1.0, 1.0] if voxel_size is None else [float(v) for v in voxel_size]
    root.attrs["multiscales"] = [{
        "version": "0.4", "name": os.path.basename(name.rstrip(os.sep)),
        "axes": [{"name": a, "type": "space", **unit} for a in "zyx"],
        "datasets": [{"path": "0", "coordinateTransformations": [
            {"type": "scale", "scale": scale}]}]}]
    return arr


def open_ome_zarr_output(path: str | os.PathLike):
    """The dataset ``0`` of an OME-Zarr image written by :func:`create_ome_zarr`, open
    for writing (a resumed run); every chunk is written whole, empty or not."""
    zarr = _zarr()
    name = os.fspath(path)
    try:
        return zarr.open_group(name, mode="r+")["0"].with_config({"write_empty_chunks": True})
    except Exception as exc:  # zarr raises several kinds on a damaged store
        raise ValueError(f"{name!r} is not an OME-Zarr output to resume ({exc})") from exc


def missing_chunks(arr, path: str | os.PathLike) -> list[tuple[int, int, int]]:
    """The chunk indices (iz, iy, ix) of :func:`create_ome_zarr`'s dataset at ``path``
    that hold no written chunk yet, in order; the store's leftover temporary files (a
    writer killed mid-chunk) are removed."""
    root = os.path.join(os.fspath(path), "0")
    for folder, _, files in os.walk(root):
        for f in files:
            if f.endswith(".partial"):
                os.remove(os.path.join(folder, f))
    grid = [-(-n // c) for n, c in zip(arr.shape, arr.chunks, strict=True)]
    return [idx for idx in np.ndindex(*grid)
            if not os.path.exists(os.path.join(root, *(str(i) for i in idx)))]


__all__ = ["UNITS_UM", "create_ome_zarr", "is_ome_zarr", "missing_chunks",
           "open_ome_zarr_output", "read_ome_zarr"]
