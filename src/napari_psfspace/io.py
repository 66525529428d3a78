"""Reading and writing images: TIFF with physical sampling, PNG figures.

Every writer is atomic (a temporary file renamed on success), so an interrupted run
never leaves a half-written file where a user's file was.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from .core.common.atomic import atomic_open
from .core.common.validate import check_memory


@dataclass(frozen=True)
class ImageInfo:
    """What a TIFF says about its sampling.

    Attributes
    ----------
    pixel_size : float or None
        Pixel size in micrometres (from the ImageJ metadata or the resolution tags).
    z_spacing : float or None
        Distance between slices in micrometres.
    shape : tuple of int
        Shape of the full array in the file.
    axes : str
        Axes as tifffile reports them (e.g. "ZYX").
    """

    pixel_size: float | None
    z_spacing: float | None
    shape: tuple[int, ...]
    axes: str


def _pixel_size_from_tags(page) -> float | None:
    tag = page.tags.get("XResolution")
    unit = page.tags.get("ResolutionUnit")
    if tag is None:
        return None
    num, den = tag.value
    if num <= 0 or den <= 0:
        return None
    per_unit = num / den  # pixels per unit
    if per_unit == 1.0:  # the default when nothing was set
        return None
    unit_value = getattr(unit, "value", 1) if unit is not None else 1
    size = 1.0 / per_unit
    if int(unit_value) == 3:  # centimetre
        return size * 1e4
    if int(unit_value) == 2:  # inch
        return size * 25400.0
    return size  # ImageJ writes micrometres with no unit (value 1)


def read_image(path: str | os.PathLike, *, index: int | None = None):
    """Read a 2-D image (or one slice of a stack) and its sampling from a TIFF file.

    Parameters
    ----------
    path : str or path-like
        TIFF file.
    index : int, optional
        Slice of a 3-D stack to return, from 0. Required for stacks; a 2-D file takes
        None or 0.

    Returns
    -------
    image : ndarray of shape (M, N)
        Pixel values in the file's dtype.
    info : ImageInfo

    Raises
    ------
    ValueError
        A stack without ``index``, an index out of range, more than 3 dimensions, a
        colour or complex image, a file that is not a readable TIFF.
    """
    data, info = _read_tiff(path)
    name = os.fspath(path)
    if data.ndim == 2:
        if index not in (None, 0):
            raise ValueError(f"--slice {index}: {name!r} is one 2-D image, not a stack "
                             "(leave --slice out)")
        return data, info
    if data.ndim != 3:
        raise ValueError(
            f"{name!r} holds an array of shape {data.shape}; expected a 2-D image "
            "or a 3-D stack (Z, Y, X)."
        )
    if index is None:
        best = best_focus_index(data)
        raise ValueError(
            f"{name!r} is a stack of {data.shape[0]} slices of {data.shape[1:]}: "
            f"choose one (`index`, or --slice on the command line), e.g. --slice {best}: "
            f"slice {best} is where the beads are most concentrated, the one in focus."
        )
    index = _slice_index(index, data.shape[0], name)
    return data[index], info


def _slice_index(index, n: int, name: str) -> int:
    """``index`` checked against a stack of ``n`` slices (no negative counting from the
    end: a slice number is the one the microscope's software shows)."""
    ok = isinstance(index, (int, np.integer)) and not isinstance(index, bool)
    if not ok or not 0 <= int(index) < n:
        raise ValueError(f"--slice {index!r} is out of range: {name!r} has {n} slices "
                         f"(0 to {n - 1}).")
    return int(index)


#: OME length units in micrometres.
_OME_UNITS = {"µm": 1.0, "um": 1.0, "nm": 1e-3, "mm": 1e3, "m": 1e6, "Å": 1e-4}


def _ome_sampling(xml: str | None) -> tuple[float | None, float | None]:
    """The pixel size and the plane spacing (µm) of an OME-XML's first image; None for
    either it does not give (or gives in a unit not known)."""
    import xml.etree.ElementTree as ET

    if not xml:
        return None, None
    try:
        root = ET.fromstring(xml)
    except ET.ParseError:
        return None, None
    pixels = next((el for el in root.iter() if el.tag.endswith("}Pixels")
                   or el.tag == "Pixels"), None)
    if pixels is None:
        return None, None

    def size(axis: str) -> float | None:
        value = pixels.get(f"PhysicalSize{axis}")
        factor = _OME_UNITS.get(pixels.get(f"PhysicalSize{axis}Unit", "µm"))
        try:
            v = float(value) * factor if value is not None and factor else None
        except ValueError:
            return None
        return v if v and np.isfinite(v) and v > 0 else None

    return size("X"), size("Z")


def _read_tiff(path, lazy: bool = False) -> tuple[np.ndarray, ImageInfo]:
    """The first series of a TIFF as a real array (squeezed beyond 3-D) and its
    :class:`ImageInfo`. Colour (RGB) and complex files are refused. ``lazy``: a dask
    array reading the file a page at a time (tifffile's Zarr view of it)."""
    name = os.fspath(path)
    if os.path.isdir(name):
        raise ValueError(f"{name!r} is a folder, expected a TIFF file")
    try:
        tif = tifffile.TiffFile(name)
    except FileNotFoundError:
        raise
    except (tifffile.TiffFileError, OSError, ValueError, EOFError) as exc:
        raise ValueError(f"{name!r} is not a readable TIFF file ({exc})") from exc
    with tif:
        try:
            series = tif.series[0]
        except IndexError:  # a header and no image directory: cut short
            raise ValueError(f"{name!r} is not a readable TIFF file (it holds no image: "
                             "cut short after its header?)") from None
        if "S" in series.axes:
            raise ValueError(f"{name!r} is a colour image (axes {series.axes}, "
                             f"{series.shape}): export the bead channel as a grey-level "
                             "image or stack")
        if not lazy:  # its decoded size, before it is read
            check_memory(float(np.prod(series.shape)) * np.dtype(series.dtype).itemsize,
                         f"{name!r} ({' x '.join(map(str, series.shape))} "
                         f"{np.dtype(series.dtype).name} values) read into memory",
                         hint="Crop it, or read a 3-D stack as OME-Zarr with --memory.")
        try:
            data = _lazy_tiff(name, series) if lazy else series.asarray()
        except Exception as exc:  # a damaged strip: tifffile raises many kinds
            raise ValueError(f"{name!r}: damaged TIFF, its pixels cannot be read "
                             f"({type(exc).__name__}: {exc})") from exc
        ij = tif.imagej_metadata or {}
        pixel = _pixel_size_from_tags(tif.pages[0])
        unit = str(ij.get("unit", "um")).lower().replace("\\u00b5", "u").replace("µ", "u")
        if pixel is not None and unit in ("nm", "nanometer"):
            pixel /= 1000.0
        z = ij.get("spacing")
        z = float(z) if z else None
        if tif.is_ome:  # OME-XML's physical sizes, where it gives them
            ome_pixel, ome_z = _ome_sampling(tif.ome_metadata)
            pixel, z = ome_pixel or pixel, ome_z or z
        info = ImageInfo(pixel, z, tuple(data.shape), series.axes)
    if data.dtype.kind not in "uif" and data.dtype != bool:
        raise ValueError(f"{name!r} holds {data.dtype} values; expected real intensities "
                         "(integers or floats)")
    if data.ndim > 3:
        data = data.reshape([n for n in data.shape if n != 1]) if lazy else np.squeeze(data)
    return data, info


def _lazy_tiff(name: str, series):
    """The first series of a TIFF as a dask array on tifffile's Zarr view of it (a
    tifffile too old for the installed Zarr: read whole, as a dask array)."""
    import dask.array as da

    try:
        import zarr

        return da.from_zarr(zarr.open(tifffile.imread(name, aszarr=True), mode="r"))
    except (TypeError, ValueError, ImportError, AttributeError, NotImplementedError):
        return da.from_array(series.asarray())


def read_array(path: str | os.PathLike) -> tuple[np.ndarray, ImageInfo]:
    """Read a TIFF's first series as it is (a 2-D image or a 3-D stack, squeezed beyond
    three dimensions) and its sampling, in one pass over the file.

    Returns
    -------
    data : ndarray of shape (M, N) or (Z, M, N)
    info : ImageInfo

    Raises
    ------
    ValueError
        A colour or complex image, a file that is not a readable TIFF.
    """
    return _read_tiff(path)


def read_stack(path: str | os.PathLike, *, lazy: bool = False):
    """Read a z-stack (Z, Y, X) and its sampling from a TIFF file (ImageJ or OME) or an
    OME-Zarr folder (:mod:`napari_psfspace.ome_zarr`).

    Parameters
    ----------
    path : str or PathLike
    lazy : bool
        Return a dask array that reads the file a piece at a time when computed (a
        stack larger than memory).

    Returns
    -------
    stack : ndarray or dask.array.Array of shape (Z, M, N)
        Pixel values in the file's dtype.
    info : ImageInfo
        ``pixel_size`` and ``z_spacing`` in µm where the file gives them.

    Raises
    ------
    ValueError
        A 2-D image, more than 3 dimensions, a colour or complex image, a file that is
        not a readable TIFF.
    """
    from .ome_zarr import is_ome_zarr, read_ome_zarr

    if is_ome_zarr(path):
        data, pixel, z, axes = read_ome_zarr(path, lazy=lazy)
        info = ImageInfo(pixel, z, tuple(data.shape), axes)
    else:
        data, info = _read_tiff(path, lazy=lazy)
    if data.ndim != 3:
        raise ValueError(f"{os.fspath(path)!r} holds an array of shape {data.shape}; "
                         "expected a z-stack (Z, Y, X)")
    return data, info


def read_slice(path: str, index: int | None) -> np.ndarray:
    """One image of a file (``index``: its slice; None for a 2-D image). Module level, so
    that a ``functools.partial`` of it is a loader a dask worker can unpickle."""
    return read_image(path, index=index)[0]


def stack_loaders(inputs: list[str], slices: str | None = None) -> tuple[list, list[str]]:
    """Zero-argument loaders, one per image, and a label for each.

    ``inputs``: TIFF files (each 2-D, or a stack whose slices are the conditions) or one
    folder of TIFFs (sorted by name). ``slices``: ``"A:B"`` (``B`` excluded) keeps those
    slices of a stack. Each image is read when its loader is called.

    Raises
    ------
    ValueError
        An input that is neither a file nor a folder, a folder without TIFFs, a bad
        ``slices``, or a file that is neither 2-D nor a (Z, Y, X) stack.
    """
    import functools

    files: list[Path] = []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            found = sorted(q for q in path.iterdir()
                           if q.suffix.lower() in (".tif", ".tiff") and q.is_file())
            if not found:
                raise ValueError(f"INPUT folder {path} holds no .tif/.tiff file")
            files += found
        elif path.is_file():
            files.append(path)
        else:
            raise ValueError(f"INPUT {path} is neither a file nor a folder")
    lo = hi = None
    if slices:
        try:
            a, b = slices.split(":")
            lo, hi = (int(a) if a else None), (int(b) if b else None)
        except ValueError:
            raise ValueError(f"--slices must be A:B (B excluded), got {slices!r}") from None
        if len(files) != 1:
            raise ValueError(f"--slices {slices} picks slices of one stack; got {len(files)} "
                             "files (pass the stack alone, or leave --slices out)")
    loaders, labels = [], []
    for f in files:
        try:
            with tifffile.TiffFile(f) as tif:
                shape = tif.series[0].shape
                axes = tif.series[0].axes
        except (tifffile.TiffFileError, OSError, ValueError, EOFError) as exc:
            raise ValueError(f"INPUT {f} is not a readable TIFF file ({exc})") from exc
        if "S" in axes:
            raise ValueError(f"INPUT {f} is a colour image (axes {axes}): export the bead "
                             "channel as a grey-level image or stack")
        shape = tuple(n for n in shape if n != 1) if len(shape) > 3 else tuple(shape)
        if slices and len(shape) == 3:
            n = shape[0]
            if (lo is not None and not 0 <= lo < n) or (hi is not None and not 0 < hi <= n) \
                    or (lo or 0) >= (n if hi is None else hi):
                raise ValueError(f"--slices {slices} is out of range: {f.name} has {n} slices "
                                 f"(A:B with 0 <= A < B <= {n})")
        elif slices:
            raise ValueError(f"--slices {slices} picks slices of a stack; {f.name} is one "
                             "2-D image")
        if len(shape) == 2:
            loaders.append(functools.partial(read_slice, str(f), None))
            labels.append(f.name)
        elif len(shape) == 3:
            for z in range(shape[0])[slice(lo, hi)]:
                loaders.append(functools.partial(read_slice, str(f), z))
                labels.append(f"{f.name}[{z}]")
        else:
            raise ValueError(f"{f} has shape {shape}: expected 2-D images or a (Z, Y, X) stack")
    return loaders, labels


def read_points_csv(path: str | os.PathLike) -> np.ndarray:
    """Bead positions (N, 2) (row, column), pixels, from a CSV file.

    Reads napari's *File > Save Selected Layer* CSV of a Points layer (columns
    ``axis-0, axis-1[, axis-2]``: the last two are row and column) or a plain table of
    two numeric columns (row, column), with or without a header line.
    """
    import csv

    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not a CSV text file (binary content: a TIFF?); "
                         "expected bead positions as row,column lines") from None
    except csv.Error as exc:
        raise ValueError(f"{path} is not a readable CSV file ({exc})") from None
    if not rows:
        raise ValueError(f"{path} holds no bead position")
    header = rows[0]
    numeric = True
    try:
        [float(c) for c in header]
    except ValueError:
        numeric = False
    body, cols = rows, None
    if not numeric:
        body = rows[1:]
        names = [c.strip() for c in header]
        axes = sorted((n for n in names if n.startswith("axis-")),
                      key=lambda n: int(n.split("-")[1]))
        cols = [names.index(n) for n in axes[-2:]] if len(axes) >= 2 else None
        if cols is None and len(names) != 2:
            raise ValueError(f"{path}: expected napari's axis-0, axis-1 columns or two "
                             f"columns (row, column), got {names}")
    try:
        pts = np.array([[float(r[i]) for i in (cols or (0, 1))] for r in body])
    except (ValueError, IndexError) as exc:
        raise ValueError(f"{path}: a row is not two numbers (row, column): {exc}") from None
    if pts.ndim != 2 or len(pts) == 0:
        raise ValueError(f"{path} holds no bead position")
    return pts


def best_focus_index(stack: np.ndarray) -> int:
    """Index of the slice in focus: where the beads concentrate their light
    (:func:`napari_psfspace.core.beads.focus.best_focus_index`; not raw contrast, which
    prefers a defocused ring at high NA)."""
    from .core.beads.focus import best_focus_index as best

    return best(stack)


def write_tiff(path: str | os.PathLike, data: np.ndarray, *, pixel_size: float | None = None,
               metadata: dict | None = None, z_spacing: float | None = None,
               into=None) -> None:
    """Write an array as an ImageJ-compatible TIFF, atomically.

    Parameters
    ----------
    path : str or path-like
    data : ndarray of 2 or 3 dimensions
        Image (Y, X) or stack (Z, Y, X). float64 is stored as float32 (ImageJ).
    pixel_size : float, optional
        Pixel size in micrometres, stored as resolution tags.
    z_spacing : float, optional
        A stack's plane spacing in micrometres (ImageJ's ``spacing``).
    into : file object, optional
        Write the TIFF's bytes into this open file instead (a set's member).
    metadata : dict, optional
        Extra JSON-serialisable information, stored in the ImageJ "Info" field.
    """
    arr = np.asarray(data)
    if arr.dtype == np.float64:
        arr = arr.astype(np.float32)
    ij = {"unit": "um", "axes": "ZYX" if arr.ndim == 3 else "YX"}
    if metadata:
        ij["Info"] = json.dumps(metadata)
    if z_spacing and arr.ndim == 3:
        ij["spacing"] = float(z_spacing)
    kwargs = {}
    if pixel_size:
        kwargs["resolution"] = (1.0 / pixel_size, 1.0 / pixel_size)
    buf = io.BytesIO()  # tifffile needs a named or in-memory file
    tifffile.imwrite(buf, arr, imagej=True, metadata=ij, **kwargs)
    if into is not None:
        into.write(buf.getbuffer())
        return
    with atomic_open(path) as fh:
        fh.write(buf.getbuffer())


def write_tiff_set(members: list[tuple[str | os.PathLike, np.ndarray, dict | None]], *,
                   pixel_size: float | None = None) -> None:
    """Write several TIFFs as one set (:func:`~.core.common.atomic.write_set`): never
    files of one run beside files of another, the first (the main output) present only
    once all are. Each member is ``(path, data, metadata)``; every file's ImageJ "Info"
    names the set's files (``"set"``) and the write they came from (``"set_run"``)."""
    import uuid

    from .core.common.atomic import write_set

    names = [os.path.basename(os.fspath(p)) for p, _, _ in members]
    run = uuid.uuid4().hex  # the same in every member of this write: a set is one run's

    def writer(path, data, meta):
        info = {**(meta or {}), "set": names, "set_run": run}
        return lambda fh: write_tiff(path, data, pixel_size=pixel_size, metadata=info,
                                     into=fh)

    write_set([(p, writer(p, d, m)) for p, d, m in members])


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write a 2-D (grey) or (M, N, 3) (RGB) array as an 8-bit PNG, atomically.

    Floating images are scaled from their [min, max] to [0, 255].
    """
    data = png_bytes(image)
    with atomic_open(path) as fh:
        fh.write(data)


def png_bytes(image: np.ndarray) -> bytes:
    """The 8-bit PNG file of a 2-D (grey) or (M, N, 3) (RGB) array (floating images
    scaled from their [min, max] to [0, 255])."""
    from PIL import Image

    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        a = arr.astype(np.float64)
        lo, hi = float(np.nanmin(a)), float(np.nanmax(a))
        a = (a - lo) / (hi - lo) if hi > lo else np.zeros_like(a)
        arr = np.round(255 * np.clip(a, 0, 1)).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def folder_writable(folder: Path) -> bool:
    """Writable by its permission bits (os.access is always true for root, which would
    let a default land in a read-only data folder)."""
    import stat

    try:
        mode = folder.stat().st_mode
    except OSError:
        return False
    return bool(mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)) and os.access(folder,
                                                                                     os.W_OK)


def check_output_file(path: str | os.PathLike, option: str) -> Path:
    """Check, before any work, that a file can be written at ``path``: not a folder, in a
    folder that exists and is writable, not a read-only file. ``option`` names it in the
    message (e.g. ``-o``)."""
    if not os.fspath(path).strip():
        raise ValueError(f"{option}: an empty path; expected a file name")
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{option} {path}: is a folder, expected a file name")
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"{option} {path}: folder {folder} does not exist")
    if not folder_writable(folder):
        raise ValueError(f"{option} {path}: folder {folder} is not writable")
    if p.exists() and not file_writable(p):
        raise ValueError(f"{option} {path}: the file exists and is read-only")
    return p


def _same_place(a: str, b: str) -> bool:
    """Whether two paths name the same file or folder (links and ``..`` resolved; one
    file under two hard-linked names too)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one does not exist yet
        return False


def check_distinct(outputs: dict[str, object], inputs: dict[str, object]) -> None:
    """Check, before any work, that no output path is an input or another output.

    Parameters
    ----------
    outputs, inputs : dict of {option: path or list of paths}
        The paths, by the option that names them in the message (``-o``,
        ``--truth-grid``, ``IMAGE``); None or "" entries are skipped.
    """
    def flat(named: dict[str, object]) -> list[tuple[str, str]]:
        out = []
        for option, value in named.items():
            values = value if isinstance(value, (list, tuple)) else [value]
            out += [(option, os.fspath(v)) for v in values if v not in (None, "")]
        return out

    outs, ins = flat(outputs), flat(inputs)
    for i, (o_opt, o_path) in enumerate(outs):
        for i_opt, i_path in ins:
            if _same_place(o_path, i_path):
                raise ValueError(f"{o_opt} {o_path} is the input {i_opt}: writing it would "
                                 "overwrite what is read; give another path")
        for o2_opt, o2_path in outs[i + 1:]:
            if _same_place(o_path, o2_path):
                raise ValueError(f"{o_opt} and {o2_opt} are the same path {o_path}: one "
                                 "output would overwrite the other")


def check_output_folder(path: str | os.PathLike, option: str) -> Path:
    """Check, before any work, that ``path`` is a writable folder or can be made one."""
    if not os.fspath(path).strip():
        raise ValueError(f"{option}: an empty path; expected a folder name")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{option} {path}: is a file, expected a folder")
    if p.is_dir():
        if not folder_writable(p):
            raise ValueError(f"{option} {path}: folder is not writable")
        return p
    parent = p.parent if str(p.parent) else Path(".")
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not folder_writable(parent):
        raise ValueError(f"{option} {path}: cannot be created ({parent} is not a writable "
                         "folder)")
    return p


def file_writable(path: Path) -> bool:
    import stat

    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return bool(mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
