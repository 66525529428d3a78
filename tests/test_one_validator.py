"""One validator per input kind, and every door calls it: the same bad input gets the
same one line from every function and command that takes it.

Kinds: the 2-D image (:func:`~napari_psfspace.core.common.validate.as_image`), the
z-stack (``as_stack``), the camera's values (``check_camera``), the model file
(``load_operator``: the archive's reader and ``check_model_field``), the family file
(``load_family``) and the 3-D model file (``load_operator_3d``). Each test computes the
validator's own message and asks every door for exactly that line, so a door with a
check of its own (another wording, or none) fails here.
"""

from __future__ import annotations

import contextlib
import io
import itertools

import numpy as np
import pytest
import tifffile

import napari_psfspace as ps
from napari_psfspace.cli import main
from napari_psfspace.core.beads.noise import NoiseModel, noise_model
from napari_psfspace.core.common.validate import as_image, as_stack, check_camera
from napari_psfspace.core.model.operator_file import read_archive, write_archive

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


def _message(call) -> str:
    with pytest.raises((ValueError, TypeError)) as info:
        call()
    return str(info.value)


def _op2d(shape=(64, 64)):
    rng = np.random.default_rng(0)
    return ps.ProductConvolution(rng.random((2, 9, 9)), 0.2 + rng.random((2, 3, 3)),
                                 shape=shape, grid=(np.linspace(0, shape[0] - 1, 3),
                                                    np.linspace(0, shape[1] - 1, 3)))


def _op3d():
    rng = np.random.default_rng(1)
    return ps.ProductConvolution3D(rng.random((1, 3, 7, 7)), np.ones((1, 2, 2)),
                                   shape=(4, 32, 32), plane=1,
                                   grid=(np.array([0.0, 31]), np.array([0.0, 31])))


GOOD = ps.simulate_beads((64, 64), 3, seed=1, min_separation=12, border=8)[0].astype(float)
NAN = GOOD.copy()
NAN[3, 3] = np.nan
BAD_IMAGES = {
    "NaN": NAN, "3-D": np.stack([GOOD, GOOD]), "complex": GOOD.astype(complex),
    "empty": np.zeros((0, 64)), "text": np.full((64, 64), "a"), "1-D": GOOD[0],
    "objects": GOOD.astype(object), "ragged": [[1.0, 2.0], [3.0]],
}
IMAGE_DOORS = {
    "detect_beads": lambda im: ps.detect_beads(im, 3),
    "estimate_operator": lambda im: ps.estimate_operator(im, psf_radius=4),
    "estimate_family": lambda im: ps.estimate_family([im, GOOD], psf_radius=4),
    "diagnose": lambda im: ps.diagnose(im, psf_radius=4),
    "deblur": lambda im: ps.deblur(im, _op2d(), max_iter=2),
    "extract_patches": lambda im: ps.extract_patches(im, np.array([[30.0, 30.0]]), 4),
    "suggest_psf_radius": ps.suggest_psf_radius,
    "spot_scale": ps.spot_scale,
    "noise_model": noise_model,
}


@pytest.mark.parametrize("door", sorted(IMAGE_DOORS))
def test_every_image_door_says_what_the_image_validator_says(door):
    for kind, bad in BAD_IMAGES.items():
        want = _message(lambda bad=bad: as_image(bad))
        assert _message(lambda bad=bad: IMAGE_DOORS[door](bad)) == want, (door, kind)


@pytest.mark.parametrize("kind", ["complex", "text", "objects", "ragged"])
def test_the_operator_checks_its_vector_with_the_same_validator(kind):
    """``apply``/``adjoint`` take any real image of the model's shape (negative values
    included: a linear operator's input), refused by the same dtype check."""
    bad = BAD_IMAGES[kind]
    op = _op2d()
    assert _message(lambda: op.apply(bad)) == _message(lambda: as_image(bad, name="u"))
    assert _message(lambda: op.adjoint(bad)) == _message(lambda: as_image(bad, name="v"))


STACK = np.random.default_rng(1).poisson(100, (4, 32, 32)).astype(float)
NAN_STACK = STACK.copy()
NAN_STACK[1, 3, 3] = np.nan
BAD_STACKS = {
    "NaN": NAN_STACK, "2-D": STACK[0], "4-D": STACK[None], "complex": STACK.astype(complex),
    "empty": np.zeros((0, 32, 32)), "text": np.full((4, 32, 32), "a"),
    "objects": STACK.astype(object), "ragged": [[[1.0, 2.0]], [[3.0]]],
}
# each door, with the requirements it gives the validator
STACK_DOORS = {
    "estimate_operator_3d": (lambda s: ps.estimate_operator_3d(s, psf_radius=3),
                             {"min_planes": 3, "min_side": 8}),
    "best_focus_index": (ps.best_focus_index, {"min_side": 8}),
    "richardson_lucy_3d": (lambda s: ps.richardson_lucy_3d(s, _op3d(), n_iter=1),
                           {"lateral": (32, 32)}),
    "deblur_3d": (lambda s: ps.deblur_3d(s, _op3d(), max_iter=1), {"lateral": (32, 32)}),
    "richardson_lucy_3d_exchange": (
        lambda s: ps.richardson_lucy_3d_exchange(s, _op3d(), n_iter=1, tile=16),
        {"lateral": (32, 32)}),
    "richardson_lucy_3d_tiled": (
        lambda s: ps.richardson_lucy_3d_tiled(s, _op3d(), n_iter=1, tile=16),
        {"lateral": (32, 32)}),
}


@pytest.mark.parametrize("door", sorted(STACK_DOORS))
def test_every_stack_door_says_what_the_stack_validator_says(door):
    call, needs = STACK_DOORS[door]
    for kind, bad in BAD_STACKS.items():
        want = _message(lambda bad=bad: as_stack(bad, **needs))
        assert _message(lambda bad=bad: call(bad)) == want, (door, kind)


@pytest.mark.parametrize("door", ["estimate_operator_3d", "richardson_lucy_3d", "deblur_3d",
                                  "richardson_lucy_3d_exchange", "richardson_lucy_3d_tiled"])
@pytest.mark.parametrize("stack", [np.zeros((4, 32, 32)), -STACK], ids=["zeros", "negated"])
def test_a_stack_without_light_is_refused_by_every_door_that_needs_it(door, stack):
    call, _ = STACK_DOORS[door]
    assert "`stack` holds no positive value" in _message(lambda: call(stack))


BAD_CAMERAS = [{"gain": 0}, {"gain": np.nan}, {"gain": 1e9}, {"offset": -1},
               {"offset": np.inf}, {"read_noise": -0.5}, {"read_noise": "x"}]
CAMERA_DOORS = {
    "simulate_beads": lambda c: ps.simulate_beads((64, 64), 2, min_separation=12, border=8,
                                                  **c),
    "simulate_focus_series": lambda c: ps.simulate_focus_series((64, 64), 2, **c),
    "diagnose": lambda c: ps.diagnose(GOOD, psf_radius=4, **c),
    "noise_model": lambda c: noise_model(GOOD, **c),
    "NoiseModel.from_camera": lambda c: NoiseModel.from_camera(**c),
}
CAMERA = {"gain": 2.0, "offset": 100.0, "read_noise": 1.5}


@pytest.mark.parametrize("door", sorted(CAMERA_DOORS))
def test_every_camera_door_says_what_the_camera_validator_says(door):
    for bad in BAD_CAMERAS:
        values = {**CAMERA, **bad}
        want = _message(lambda v=values: check_camera(**v))
        assert _message(lambda v=values: CAMERA_DOORS[door](v)) == want, (door, bad)


# ---------------------------------------------------------------------- model files

def _damage(arr: np.ndarray, how: str) -> np.ndarray:
    a = np.array(arr, dtype=float if arr.dtype.kind != "u" else arr.dtype)
    if how == "nan":
        a.flat[a.size // 2] = np.nan
    elif how == "inf":
        a.flat[0] = np.inf
    elif how == "negated":
        a = -a
    elif how == "zero":
        a = 0 * a
    elif how == "flattened":
        a = a.ravel()
    elif how == "empty":
        a = a[:0]
    elif how == "complex":
        a = a.astype(complex)
    elif how == "text":
        a = np.full(a.shape, "a")
    elif how == "huge":
        a = a * 1e300
    elif how == "transposed":
        a = a.T.copy()
    return a


DAMAGES = ("nan", "inf", "negated", "zero", "flattened", "empty", "complex", "text", "huge",
           "transposed")


#: a new name for each example's outputs: hypothesis may run an example twice
RUN = itertools.count()


def _cli(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main([str(a) for a in argv])
    return rc, err.getvalue()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("validators")
    _op2d().save(d / "model.npz")
    _op3d().save(d / "model3d.npz")
    images = [ps.simulate_beads((128, 128), 12, seed=s, min_separation=20, border=12)[0]
              for s in range(3)]
    ps.estimate_family(images, psf_radius=5, n_psf=2).save(d / "family.npz")
    tifffile.imwrite(d / "beads.tif", GOOD.astype(np.float32))
    tifffile.imwrite(d / "beads128.tif", images[0])
    tifffile.imwrite(d / "stack.tif", STACK.astype(np.float32), imagej=True)
    return d


def _damaged_copy(src, dst, entry: str, how: str, *, fmt, version, entries, kind) -> None:
    arrays, header = read_archive(src, format_name=fmt, format_version=version,
                                  entries=entries, kind=kind)
    arrays[entry] = _damage(arrays[entry], how)
    write_archive(dst, arrays, header)


def _refusal(load) -> str | None:
    """The loader's one line for a file it refuses; None for one it loads."""
    try:
        load()
    except ValueError as exc:
        return str(exc)
    return None


def _agree(outcomes: dict[str, tuple[int, str]], api: str | None) -> None:
    """Every door: exit 0, or exit 2 whose one line holds the loader's message (the
    command line prints it on one line: its runs of spaces are one)."""
    for door, (rc, err) in outcomes.items():
        if api is None:
            assert rc == 0, (door, err)
        else:
            assert rc == 2 and " ".join(api.split()) in " ".join(err.split()), (door, api, err)
            assert len([x for x in err.splitlines() if "error" in x]) == 1, (door, err)
            assert "Traceback" not in err, (door, err)


@given(st.sampled_from(["basis", "coefficients", "grid_y", "grid_x", "shape"]),
       st.sampled_from(DAMAGES))
def test_every_model_door_agrees_about_a_damaged_model_file(files, entry, how):
    """``load_operator``, the napari reader and ``psf``, ``apply`` and ``deblur``: each
    array of the file damaged in turn, all refuse it with the loader's line, or all
    work with finite outputs."""
    from napari_psfspace._reader import read_model
    from napari_psfspace.core.model.operator_file import FORMAT_NAME, FORMAT_VERSION

    d = files
    path = d / f"m_{entry}_{how}.npz"
    _damaged_copy(d / "model.npz", path, entry, how, fmt=FORMAT_NAME, version=FORMAT_VERSION,
                  entries=("basis", "coefficients", "grid_y", "grid_x", "shape", "header"),
                  kind="model")
    api = _refusal(lambda: ps.load_operator(path))
    if api is None:
        read_model(path)
    else:
        assert _message(lambda: read_model(path)) == api
    out = d / f"out_{entry}_{how}_{next(RUN)}"
    outcomes = {
        "psf": _cli(["psf", path, "--at", 30, 30, "-o", f"{out}_p.tif"]),
        "apply": _cli(["apply", path, d / "beads.tif", "-o", f"{out}_a.tif"]),
        "deblur": _cli(["deblur", d / "beads.tif", "--model", path, "-o", f"{out}_d.tif",
                        "-q", "--max-iter", 3]),
    }
    _agree(outcomes, api)
    if api is None:
        for suffix in ("_p.tif", "_a.tif", "_d.tif"):
            assert np.isfinite(tifffile.imread(f"{out}{suffix}")).all()


@given(st.sampled_from(["basis", "coefficients", "grid_y", "grid_x", "shape"]),
       st.sampled_from(DAMAGES))
def test_every_3d_model_door_agrees_about_a_damaged_file(files, entry, how):
    """``load_operator_3d`` and ``deblur3d``: the same line, or both work."""
    from napari_psfspace.core.volume.operator3d import FORMAT_NAME, FORMAT_VERSION

    d = files
    path = d / f"m3_{entry}_{how}.npz"
    with np.load(d / "model3d.npz") as data:
        entries = tuple(data.files)
    if entry not in entries:
        return
    _damaged_copy(d / "model3d.npz", path, entry, how, fmt=FORMAT_NAME,
                  version=FORMAT_VERSION, entries=entries, kind="3D model")
    api = _refusal(lambda: ps.load_operator_3d(path))
    out = d / f"out3_{entry}_{how}_{next(RUN)}.tif"
    _agree({"deblur3d": _cli(["deblur3d", d / "stack.tif", "--model", path, "-o", out,
                              "--iterations", 2, "-q"])}, api)
    if api is None:
        assert np.isfinite(tifffile.imread(out)).all()


@given(st.sampled_from(DAMAGES))
def test_every_family_door_agrees_about_a_damaged_family_file(files, how):
    """``load_family``, ``psf --image`` and ``deblur --family``: the same line, or all
    work."""
    from napari_psfspace.core.family.family_file import FORMAT_NAME, FORMAT_VERSION

    d = files
    with np.load(d / "family.npz") as data:
        entries = tuple(data.files)
    for entry in [e for e in entries if e != "header"]:
        path = d / f"f_{entry}_{how}.npz"
        _damaged_copy(d / "family.npz", path, entry, how, fmt=FORMAT_NAME,
                      version=FORMAT_VERSION, entries=entries, kind="family")
        api = _refusal(lambda path=path: ps.load_family(path))
        out = d / f"outf_{entry}_{how}_{next(RUN)}"
        _agree({"psf": _cli(["psf", path, "--image", 0, "--at", 60, 60, "-o",
                             f"{out}_p.tif"]),
                "deblur": _cli(["deblur", d / "beads128.tif", "--family", path, "-o",
                                f"{out}_d.tif", "-q", "--max-iter", 3])}, api)
