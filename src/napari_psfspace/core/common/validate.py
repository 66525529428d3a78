"""Input checks shared by the core: one place for uniform, explicit error messages.

Every message names the parameter, what was expected and what was received.
"""

from __future__ import annotations

import numpy as np


def as_array(value, name: str) -> np.ndarray:
    """``value`` as an array without copying one that is already an array (NumPy, or a
    lazy dask or Zarr array, whose ``shape`` and ``dtype`` are read without its data);
    nested sequences of unequal lengths are refused naming ``name``."""
    if hasattr(value, "shape") and hasattr(value, "dtype") and hasattr(value, "ndim"):
        return value
    try:
        return np.asarray(value)
    except (ValueError, TypeError):
        raise ValueError(f"`{name}` must be an array of numbers, got a {type(value).__name__} "
                         "that does not make one (rows of unequal lengths?)") from None


def check_dtype(arr, name: str) -> None:
    """ValueError naming ``name`` unless ``arr`` holds real numbers (bool, integer or
    float): complex, text and object arrays are refused."""
    kind = np.dtype(arr.dtype).kind
    if kind == "c":
        raise ValueError(f"`{name}` must be real-valued, got complex dtype {arr.dtype}.")
    if kind not in "biuf":
        raise ValueError(f"`{name}` must be a numeric array, got dtype {arr.dtype}.")


def check_finite(arr: np.ndarray, name: str) -> None:
    """ValueError naming ``name`` and counting the NaN or infinite values of ``arr``."""
    if arr.dtype.kind != "f":
        return
    finite = np.isfinite(arr)
    if not finite.all():
        n_bad = int(arr.size - np.count_nonzero(finite))
        raise ValueError(
            f"`{name}` contains {n_bad} NaN or infinite value(s); expected only finite "
            "values. Mask or inpaint them first."
        )


def as_image(image, *, name: str = "image", dtype=None, copies: float = 0.0) -> np.ndarray:
    """Check a 2-D single-plane image and return it as a floating array.

    The one validator of a 2-D image: every function that takes one calls it.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Any real dtype. Integer and boolean images become float32; float32 and
        float64 are kept (float16 becomes float32).
    name : str
        Parameter name used in error messages.
    dtype : dtype, optional
        Force this floating dtype.
    copies : float
        The float32 images of this size the caller's computation holds at once: their
        memory is checked (:func:`check_memory`) before the image is converted.

    Returns
    -------
    ndarray of shape (M, N), floating

    Raises
    ------
    ValueError
        Not an array of numbers, wrong number of dimensions (a 3-D stack gets a hint to
        pass one slice), an empty image, complex values, NaN or infinite values.
    """
    arr = np.asarray(as_array(image, name))
    check_dtype(arr, name)
    if arr.ndim == 3:
        best = int(np.argmax(arr.reshape(arr.shape[0], -1).astype(np.float32).std(axis=1)))
        raise ValueError(
            f"`{name}` must be a 2-D image (rows, columns), got a 3-D stack of shape {arr.shape}. "
            f"Pass one slice, e.g. `{name}[{best}]` (slice {best} has the highest contrast; "
            "`napari_psfspace.best_focus_index` finds the slice where the beads are in "
            "focus), or learn a 3-D PSF from the whole bead stack with "
            "`napari_psfspace.estimate_operator_3d` (`psfspace estimate3d`)."
        )
    if arr.ndim != 2:
        raise ValueError(
            f"`{name}` must be a 2-D image (rows, columns), got {arr.ndim} dimension(s) "
            f"with shape {arr.shape}."
        )
    if arr.size == 0 or min(arr.shape) < 2:
        raise ValueError(f"`{name}` must be a non-empty 2-D image, got shape {arr.shape}.")
    if copies:
        check_memory(copies * 4.0 * arr.size, f"`{name}` of {arr.shape[0]} x {arr.shape[1]} "
                     f"pixels ({copies:g} float32 images of its size at once)",
                     hint="Crop it, or bin it.")
    if dtype is None:
        dtype = np.float64 if arr.dtype == np.float64 else np.float32
    out = arr.astype(dtype, copy=False)
    check_finite(out, name)
    return out


def as_stack(stack, *, name: str = "stack", lateral: tuple[int, int] | None = None,
             min_planes: int = 1, min_side: int = 2, finite: bool = True,
             copies: float = 0.0):
    """Check a z-stack (Z, H, W) and return it, unconverted (a lazy dask or Zarr stack
    stays lazy).

    The one validator of a 3-D stack: every function that takes one calls it.

    Parameters
    ----------
    stack : array_like of shape (Z, H, W)
        Any real dtype; NumPy, dask or Zarr.
    name : str
        Parameter name used in error messages.
    lateral : (int, int), optional
        The (H, W) the stack must have (an operator's field).
    min_planes, min_side : int
        The fewest planes, and the fewest pixels a plane's side may have.
    finite : bool
        Check every value is finite (in memory only: a lazy stack is checked where it
        is read).
    copies : float
        The float32 volumes of this size the caller's computation holds in memory at
        once: their memory is checked (:func:`check_memory`) before any is made.

    Raises
    ------
    ValueError
        Not an array of numbers, complex or text values, not three dimensions, too few
        planes or pixels, another lateral shape, NaN or infinite values.
    """
    arr = as_array(stack, name)
    check_dtype(arr, name)
    shape = tuple(int(n) for n in arr.shape)
    want = f"(Z, {lateral[0]}, {lateral[1]})" if lateral is not None else "(Z, H, W)"
    if len(shape) != 3:
        hint = (" (one image: pass it to the 2-D functions, or stack its planes)"
                if len(shape) == 2 else "")
        raise ValueError(f"`{name}` must be a z-stack {want}, got shape {shape}{hint}")
    if lateral is not None and shape[1:] != tuple(lateral):
        raise ValueError(f"`{name}` must be a z-stack {want}, got shape {shape}")
    if shape[0] < min_planes or min(shape[1:]) < min_side:
        raise ValueError(f"`{name}` must have at least {min_planes} plane(s) of at least "
                         f"{min_side} x {min_side} pixels, got shape {shape}")
    if copies:
        check_memory(copies * 4.0 * shape[0] * shape[1] * shape[2],
                     f"`{name}` of {shape[0]} x {shape[1]} x {shape[2]} voxels ({copies:g} "
                     "float32 volumes of its size at once)",
                     hint="Crop it, or deblur it in tiles: psfspace deblur3d --memory.")
    if finite and isinstance(arr, np.ndarray):
        check_finite(arr, name)
    return arr


def check_signal(image: np.ndarray, name: str = "image") -> None:
    """ValueError unless ``image`` (finite) can hold a fluorescence image: at least one
    positive value (light is counted up from zero; a negated or empty image has none)
    and not one value everywhere (no bead stands above its background)."""
    lo, hi = float(np.min(image)), float(np.max(image))
    if not hi > 0:
        raise ValueError(f"`{name}` holds no positive value (largest {hi:g}); expected a "
                         "fluorescence image, counts >= 0 with beads above the background")
    if hi == lo:
        raise ValueError(f"`{name}` is constant (every value {hi:g}); expected beads above "
                         "a background")


#: Gains of real cameras, ADU per electron: from a deep-well CCD's (well below one) to
#: an EMCCD's with its multiplication (thousands); outside, the image is one value or
#: every bead saturates.
GAIN_RANGE = (1e-3, 1e4)


def check_camera(gain, offset, read_noise, dtype=None
                 ) -> tuple[float | None, float | None, float | None, np.dtype | None]:
    """The one validator of a camera's values: ``gain`` (ADU per electron) finite and
    within :data:`GAIN_RANGE`, ``offset`` (ADU) finite and >= 0 (and below the largest
    count of ``dtype``), ``read_noise`` (electrons rms) finite and >= 0, ``dtype`` an
    unsigned integer (counts) or a float. A value given as None is not checked (a
    measured one stands for it) and comes back None. Returns
    ``(gain, offset, read_noise, dtype)`` as floats and a NumPy dtype."""
    out: list[float | None] = []
    for name, value, low, strict in (("gain", gain, 0.0, True), ("offset", offset, 0.0, False),
                                     ("read_noise", read_noise, 0.0, False)):
        if value is None:
            out.append(None)
            continue
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"`{name}` must be a number, got {value!r}") from None
        if not np.isfinite(v) or (v <= low if strict else v < low):
            raise ValueError(f"`{name}` must be a finite number {'>' if strict else '>='} "
                             f"{low:g}, got {value!r}")
        out.append(v + 0.0)  # -0.0 is 0
    if out[0] is not None and not GAIN_RANGE[0] <= out[0] <= GAIN_RANGE[1]:
        raise ValueError(f"`gain` must be a camera's, {GAIN_RANGE[0]:g} to {GAIN_RANGE[1]:g} "
                         f"ADU per electron, got {gain!r}")
    if dtype is None:
        return out[0], out[1], out[2], None
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"`dtype` must be a NumPy dtype, got {dtype!r}") from None
    if dt.kind not in "uf":
        raise ValueError(f"`dtype` must be an unsigned integer (a camera's counts) or a "
                         f"float, got {dt}")
    # integers: the dtype's range; floats: the counts they hold exactly
    top = np.iinfo(dt).max if dt.kind == "u" else 2.0 ** (np.finfo(dt).nmant + 1)
    if out[1] is not None and not out[1] < top:
        raise ValueError(f"`offset` {out[1]:g} must be below {top:g}, the largest count "
                         f"{dt} holds exactly")
    return out[0], out[1], out[2], dt


def check_exposure(gain: float, offset: float, background: float, dtype) -> None:
    """ValueError unless a camera of ``gain`` (ADU per electron) and ``offset`` (ADU)
    records a ``background`` (photo-electrons a pixel, the largest drawn) below the
    largest count of an integer ``dtype``: at or above it, every pixel saturates and the
    image holds one value."""
    dt = np.dtype(dtype)
    if dt.kind not in "ui":
        return
    level, top = offset + gain * background, float(np.iinfo(dt).max)
    if not level < top:
        raise ValueError(f"`gain` {gain:g} and `offset` {offset:g} put the background (up "
                         f"to {background:g} photons) at {level:g} ADU, at or above {dt}'s "
                         f"largest count {top:g}: every pixel would saturate; lower `gain` "
                         "or `background`, or give a wider `dtype`")


def check_background(background, top: float, name: str = "background") -> float:
    """A constant background: finite and below ``top``, the data's largest value (at or
    above it, every iteration would drive the estimate to zero)."""
    try:
        b = float(background)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a number, got {background!r}") from None
    if not np.isfinite(b):
        raise ValueError(f"`{name}` must be finite, got {background!r}")
    if not b < top:
        raise ValueError(f"`{name}` {b:g} is at or above the data's largest value {top:g}: "
                         "nothing would be left to deblur; give a background below it")
    return b


def check_positive(value, name: str, *, allow_zero: bool = False) -> float:
    """Return ``float(value)`` after checking it is finite and positive."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a number, got {value!r}.") from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        expected = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"`{name}` must be finite and {expected}, got {value!r}.")
    return v


def check_threshold(value, name: str) -> float:
    """Return ``float(value)`` after checking it is a positive number; ``inf`` (nothing
    exceeds it) is allowed."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a number, got {value!r}.") from None
    if np.isnan(v) or v <= 0:
        raise ValueError(f"`{name}` must be > 0 (inf: none exceeds it), got {value!r}.")
    return v


def check_psf_radius(psf_radius, shape: tuple[int, int]) -> float:
    """Check the PSF radius (pixels) against the image shape."""
    r = check_positive(psf_radius, "psf_radius")
    if r < 1.5:
        raise ValueError(
            f"`psf_radius` must be at least 1.5 pixels (the PSF must span several pixels), "
            f"got {psf_radius!r}."
        )
    if 2 * r + 1 > min(shape):
        raise ValueError(
            f"`psf_radius` = {psf_radius!r} pixels is too large for an image of shape {shape}: "
            f"expected 2 * psf_radius + 1 <= {min(shape)}."
        )
    return r


def check_int(value, name: str, *, minimum: int | None = None,
              maximum: int | None = None) -> int:
    """Return ``int(value)`` after checking it is a whole number within the bounds.

    ``2.0`` passes as 2; ``2.5``, ``"3"``, ``True`` and NaN are refused with an error that
    names ``name``.
    """
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if not ok and isinstance(value, (float, np.floating)) and np.isfinite(value) \
            and float(value).is_integer():
        ok = True
    if not ok:
        raise ValueError(f"`{name}` must be a whole number, got {value!r}.")
    v = int(value)
    if (minimum is not None and v < minimum) or (maximum is not None and v > maximum):
        lo = "-inf" if minimum is None else minimum
        hi = "inf" if maximum is None else maximum
        raise ValueError(f"`{name}` must be in [{lo}, {hi}], got {value!r}.")
    return v


def check_n_psf(n_psf, name: str = "n_psf") -> int | None:
    """Check a basis size: a positive whole number, ``'heldout'``, ``'rule'`` or None.
    Returns the fixed size (an int), or None when the data choose it."""
    if n_psf is None or (isinstance(n_psf, str) and n_psf in ("heldout", "rule")):
        return None
    try:
        bad = (isinstance(n_psf, (bool, np.bool_, str)) or int(n_psf) != n_psf
               or n_psf < 1)
    except (TypeError, ValueError, OverflowError):
        bad = True
    if bad:
        raise ValueError(f"`{name}` must be a positive integer, 'heldout', 'rule' or None, "
                         f"got {n_psf!r}.")
    return int(n_psf)


def check_grid_step(grid_step, shape: tuple[int, ...], name: str = "grid_step", *,
                    minimum: float = 1.0) -> float:
    """Check a coarse grid's spacing (pixels): finite, at least ``minimum``, at most the
    image's larger side (a larger step leaves one node: no field)."""
    step = check_positive(grid_step, name)
    if step < minimum or step > max(shape):
        raise ValueError(f"`{name}` must be between {minimum:g} and the image's larger side "
                         f"({max(shape)} px), got {grid_step!r}.")
    return step


def check_saturation(saturation, name: str = "saturation") -> float | None:
    """None, or a finite positive level (image units): no camera saturates at zero or
    below, and a level there would mark every bead saturated."""
    if saturation is None:
        return None
    try:
        v = float(saturation)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a number or None, got {saturation!r}.") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"`{name}` must be a positive level in image units (or None: the "
                         f"dtype's maximum for integer images), got {saturation!r}.")
    return v


def check_instance(value, cls: type, name: str, hint: str = "") -> None:
    """Raise a TypeError naming ``name`` when ``value`` is not a ``cls``."""
    if not isinstance(value, cls):
        article = "an" if cls.__name__[0] in "AEIOU" else "a"
        raise TypeError(f"`{name}` must be {article} {cls.__name__}, got "
                        f"{type(value).__name__}.{(' ' + hint) if hint else ''}")


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``; else the
    free physical pages), or None where neither can be read."""
    import os

    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, AttributeError):
        return None


#: A computation may take at most this share of the memory available.
MEMORY_SHARE = 0.8


def check_shape(shape, name: str = "shape", *, minimum: int = 16) -> tuple[int, int]:
    """Two whole numbers of pixels (H, W), each at least ``minimum``."""
    try:
        vals = tuple(shape)
        ok = len(vals) == 2 and all(
            not isinstance(v, (bool, np.bool_)) and float(v) == int(v) for v in vals)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok or min(int(v) for v in vals) < minimum:
        raise ValueError(f"`{name}` must be two whole numbers of pixels (H, W), each at "
                         f"least {minimum}, got {shape!r}.")
    return int(vals[0]), int(vals[1])


def check_memory(nbytes: float, what: str, *, hint: str = "Ask for less.") -> None:
    """ValueError before any allocation when ``what`` needs more than
    :data:`MEMORY_SHARE` of the memory available, saying both, and ``hint``."""
    avail = available_memory()
    if avail is not None and nbytes > MEMORY_SHARE * avail:
        raise ValueError(f"{what} needs about {nbytes / 2**30:.3g} GiB of memory; this "
                         f"machine has {avail / 2**30:.3g} GiB available. {hint}")
