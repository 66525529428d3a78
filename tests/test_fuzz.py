"""Property-based doors (hypothesis): every public function and command, given images,
stacks and values a user could pass (any dtype, shape, NaN, constant, negative, tiny,
binary), either returns a result that passes its own sanity checks (finite, the right
shape, non-negative where physics says so) or refuses with a ``ValueError`` or
``TypeError`` whose one line names the argument.

Two profiles (``tests/conftest.py``): ``fast`` (the suite's, a few examples each, seeded
so that every run is the same) and ``fuzz`` (``make fuzz``: ``FUZZ_EXAMPLES`` each, 100 by
default, five times as many through the command line, random). ``HYPOTHESIS_PROFILE``
chooses.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import napari_psfspace as ps  # noqa: E402
from napari_psfspace.cli import main  # noqa: E402

DTYPES = (np.uint8, np.uint16, np.int16, np.int32, np.float32, np.float64, np.bool_)
# images with beads, of the model's shape, drawn more often: the doors that succeed are
# exercised as well as those that refuse
KINDS = ("beads",) * 4 + ("zeros", "constant", "noise", "negative", "nan", "inf", "binary",
                          "tiny")
SHAPES = ((64, 64),) * 4 + ((48, 80), (16, 16), (3, 64), (1, 1), (64,), (2, 32, 32))


def make_image(kind: str, dtype, shape, seed: int) -> np.ndarray:
    """An image of one of :data:`KINDS`, in ``dtype`` (cast as a user's file would be)."""
    rng = np.random.default_rng(seed)
    if kind == "beads" and len(shape) == 2 and min(shape) >= 48:
        img = ps.simulate_beads(shape, 3, seed=seed, min_separation=12, border=8)[0]
        img = img.astype(np.float64)
    elif kind == "zeros":
        img = np.zeros(shape)
    elif kind == "constant":
        img = np.full(shape, 7.0)
    elif kind == "negative":
        img = -rng.poisson(100, shape).astype(np.float64)
    elif kind == "binary":
        img = (rng.random(shape) < 0.05).astype(np.float64)
    elif kind == "tiny":
        img = rng.random(shape) * 1e-30
    else:
        img = rng.poisson(100, shape).astype(np.float64)
        if kind == "nan" and img.size:
            img.flat[rng.integers(img.size)] = np.nan
        if kind == "inf" and img.size:
            img.flat[rng.integers(img.size)] = np.inf
    if np.dtype(dtype).kind in "iub":
        info = np.iinfo(dtype) if np.dtype(dtype).kind != "b" else None
        img = np.nan_to_num(img, nan=0, posinf=0, neginf=0)
        if info is not None:
            img = np.clip(img, info.min, info.max)
    return img.astype(dtype)


images = st.builds(make_image, st.sampled_from(KINDS), st.sampled_from(DTYPES),
                   st.sampled_from(SHAPES), st.integers(0, 2**16))
numbers = st.one_of(st.sampled_from([0, -1, 0.5, 1, 3, 6, 1e6, np.nan, np.inf, -np.inf]),
                    st.floats(allow_nan=True, allow_infinity=True, width=32))

NAMED = re.compile(r"`[a-z_\[\]0-9 ()]+`|\b(image|stack|psf_radius|operator|shape)\b")


def refused_or_sane(call, check, *, names=()):
    """``call()``: a ``ValueError``/``TypeError`` of one line naming an argument (one of
    ``names``, or any in backticks), or a result ``check`` accepts."""
    try:
        out = call()
    except (ValueError, TypeError) as exc:
        msg = str(exc)
        assert "\n" not in msg.strip(), msg
        assert NAMED.search(msg) or any(n in msg for n in names), msg
        return None
    check(out)
    return out


def _finite(a) -> bool:
    return bool(np.all(np.isfinite(np.asarray(a, dtype=float))))


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(0)
    return ps.ProductConvolution(rng.random((2, 9, 9)), 0.2 + rng.random((2, 3, 3)),
                                 shape=(64, 64), grid=(np.linspace(0, 63, 3),) * 2)


@given(images, numbers)
def test_detect_beads(image, radius):
    def check(beads):
        assert np.all(np.isfinite(beads.positions))

    refused_or_sane(lambda: ps.detect_beads(image, radius), check)


@given(images, numbers)
def test_estimate_operator(image, radius):
    def check(est):
        op = est.operator if hasattr(est, "operator") else est
        assert _finite(op.basis) and _finite(op.coefficients)

    refused_or_sane(lambda: ps.estimate_operator(image, psf_radius=radius), check,
                    names=("bead", "beads"))


@given(images)
def test_deblur(model, image):
    def check(res):
        assert res.image.shape == model.image_shape and _finite(res.image)
        assert np.all(res.sparse >= 0)

    refused_or_sane(lambda: ps.deblur(image, model, max_iter=5), check)


@given(images)
def test_apply(model, image):
    def check(out):
        assert out.shape == model.image_shape and _finite(out)

    refused_or_sane(lambda: model.apply(image), check, names=("u",))


@given(st.builds(make_image, st.sampled_from(KINDS), st.sampled_from(DTYPES),
                 st.just((4, 32, 32)), st.integers(0, 2**16)), numbers)
def test_richardson_lucy_3d(stack, background):
    rng = np.random.default_rng(1)
    op = ps.ProductConvolution3D(rng.random((1, 3, 7, 7)), np.ones((1, 2, 2)),
                                 shape=(4, 32, 32), plane=1,
                                 grid=(np.array([0.0, 31]), np.array([0.0, 31])))
    b = None if not np.isfinite(background) or background == 0 else background

    def check(res):
        assert res.volume.shape == stack.shape and _finite(res.volume)
        assert np.all(res.volume >= 0) and res.volume.max() > 0

    refused_or_sane(lambda: ps.richardson_lucy_3d(stack, op, n_iter=2, background=b),
                    check)


@given(st.sampled_from(["gain", "offset", "read_noise"]), numbers,
       st.sampled_from(DTYPES))
def test_simulate_beads(name, value, dtype):
    def check(out):
        img = out[0]
        assert img.shape == (64, 64) and _finite(img) and np.ptp(img) > 0

    refused_or_sane(lambda: ps.simulate_beads((64, 64), 2, min_separation=12, border=8,
                                              dtype=dtype, **{name: value}), check)


@settings(max_examples=5 * settings().max_examples)
@given(images, st.sampled_from(["estimate", "deblur", "apply"]))
def test_the_command_line(tmp_path_factory, model, image, command):
    """A TIFF of any of these images through the commands: exit 0 and a finite output,
    or exit 2 and one line."""
    import contextlib
    import io

    import tifffile

    d = tmp_path_factory.mktemp("fuzz")
    model.save(d / "m.npz")
    try:
        tifffile.imwrite(d / "in.tif", image)
    except Exception:  # noqa: BLE001  a dtype tifffile cannot write: not a user's file
        return
    argv = {"estimate": ["estimate", str(d / "in.tif"), "-o", str(d / "out.npz"),
                         "--psf-radius", "5"],
            "deblur": ["deblur", str(d / "in.tif"), "--model", str(d / "m.npz"),
                       "-o", str(d / "out.tif"), "-q", "--max-iter", "5"],
            "apply": ["apply", str(d / "m.npz"), str(d / "in.tif"), "-o",
                      str(d / "out.tif")]}[command]
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(argv)
    assert rc in (0, 2)
    lines = [x for x in err.getvalue().splitlines()
             if "error" in x or "Traceback" in x]
    if rc == 2:
        assert len(lines) == 1 and "Traceback" not in err.getvalue(), err.getvalue()
        assert not (d / "out.tif").exists() and not (d / "out.npz").exists()
    elif command != "estimate":
        out = tifffile.imread(d / "out.tif")
        assert _finite(out)
