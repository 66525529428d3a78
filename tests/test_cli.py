"""The ``psfspace`` command line, end to end on small simulated data."""

import json

import numpy as np
import pytest
import tifffile

from napari_psfspace.cli import main
from napari_psfspace.core.model.operator import load_operator
from tolerances import product_convolution_errors, sum_error


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    assert main(["simulate", "-o", str(d / "beads.tif"), "--shape", "384", "384",
                 "--beads", "25", "--seed", "1", "--truth-grid", str(d / "truth.tif")]) == 0
    return d


def test_simulate_writes_image_with_pixel_size(workdir):
    with tifffile.TiffFile(workdir / "beads.tif") as tif:
        assert tif.asarray().shape == (384, 384)
        info = json.loads(tif.imagej_metadata["Info"])
    assert info["n_beads"] == 25 and info["psf_radius"] >= 4
    assert tifffile.imread(workdir / "truth.tif").shape[0] == 64


def test_estimate_psf_apply(workdir, capsys):
    d = workdir
    radius = json.loads(tifffile.TiffFile(d / "beads.tif").imagej_metadata["Info"])["psf_radius"]
    assert main(["estimate", str(d / "beads.tif"), "-o", str(d / "model.npz"),
                 "--psf-radius", str(radius), "-q"]) == 0
    out = capsys.readouterr().out
    assert "held-out error" in out and "noise floor" in out and "basis of" in out
    op = load_operator(d / "model.npz")
    assert op.image_shape == (384, 384)
    assert op.metadata["pixel_size_um"] == pytest.approx(0.065, rel=1e-3)

    assert main(["psf", str(d / "model.npz"), "--at", "100", "200", "-o",
                 str(d / "psf.tif")]) == 0
    psf = tifffile.imread(d / "psf.tif")
    # float32 values of a sum-1 PSF, summed in float32 (tests/tolerances.py)
    assert psf.shape == (op.psf_size,) * 2 and abs(psf.sum() - 1) <= sum_error(psf)

    assert main(["apply", str(d / "model.npz"), str(d / "beads.tif"), "-o",
                 str(d / "blurred.tif")]) == 0
    blurred = tifffile.imread(d / "blurred.tif")
    image = tifffile.imread(d / "beads.tif").astype(np.float32)
    assert blurred.dtype == np.float32
    # two float32 runs of H u, each within the bound of the exact one
    ref = op.apply(image)
    assert np.abs(blurred - ref).max() <= 2 * product_convolution_errors(op, image, image)[0]


def test_errors_are_one_line_messages(workdir, capsys):
    d = workdir
    stack = np.stack([tifffile.imread(d / "beads.tif")] * 3)
    tifffile.imwrite(d / "stack.tif", stack, photometric="minisblack")
    assert main(["estimate", str(d / "stack.tif"), "-o", str(d / "m.npz"),
                 "--psf-radius", "6"]) == 2
    err = capsys.readouterr().err
    assert "stack of 3 slices" in err and "Traceback" not in err
    assert not (d / "m.npz").exists()

    tifffile.imwrite(d / "small.tif", np.zeros((100, 100), np.uint16))
    assert main(["estimate", str(d / "small.tif"), "-o", str(d / "m.npz"),
                 "--psf-radius-um", "0.5"]) == 2
    assert "pixel size" in capsys.readouterr().err

    # a model of its own (not another test's file): one Gaussian PSF over 384 x 384
    from napari_psfspace.core.model.operator import ProductConvolution

    y, x = np.mgrid[-4:5, -4:5]
    psf = np.exp(-(y ** 2 + x ** 2) / 4.0)
    ProductConvolution((psf / psf.sum())[None], np.ones((1, 1, 1)), shape=(384, 384),
                       grid=(np.zeros(1), np.zeros(1))).save(d / "own.npz")
    assert main(["apply", str(d / "own.npz"), str(d / "small.tif"), "-o",
                 str(d / "x.tif")]) == 2
    assert "(384, 384)" in capsys.readouterr().err
    assert not (d / "x.tif").exists()


def test_demo_small(tmp_path, capsys):
    assert main(["demo", "--scene", "small", "--out", str(tmp_path), "-q"]) == 0
    out = capsys.readouterr().out
    assert "best single shift-invariant PSF" in out
    result = json.loads((tmp_path / "errors.json").read_text())
    # measured on the small scene: aligned mean ~0.04
    assert result["errors"]["aligned"]["mean"] < 0.08
    for name in ["image.tif", "model.npz", "psf_grid.png", "basis.png",
                 "coefficient_maps.png", "psf_grid_true.tif", "psf_grid_estimated.tif"]:
        assert (tmp_path / name).stat().st_size > 0


def test_bead_diameter_in_nanometres_and_pixel_size(workdir, capsys):
    d = workdir
    assert main(["estimate", str(d / "beads.tif"), "-o", str(d / "m200.npz"), "-q",
                 "--psf-radius", "8", "--bead-diameter-nm", "200"]) == 0
    out = capsys.readouterr().out
    assert "Bead size corrected" in out and "point source" in out
    op = load_operator(d / "m200.npz")
    assert op.metadata["bead_diameter_px"] == pytest.approx(0.2 / 0.065, rel=1e-3)
    assert op.metadata["bead_correction"]["diameter_px"] == pytest.approx(0.2 / 0.065,
                                                                          rel=1e-3)
    # a pixel size given on the command line overrides the file's
    assert main(["estimate", str(d / "beads.tif"), "-o", str(d / "m100.npz"), "-q",
                 "--psf-radius", "8", "--bead-diameter-nm", "200",
                 "--pixel-size-nm", "100"]) == 0
    capsys.readouterr()
    assert load_operator(d / "m100.npz").metadata["bead_diameter_px"] == pytest.approx(2.0)
    # no pixel size: refused, naming the fix
    tifffile.imwrite(d / "nopx.tif", tifffile.imread(d / "beads.tif"))
    assert main(["estimate", str(d / "nopx.tif"), "-o", str(d / "x.npz"),
                 "--psf-radius", "8", "--bead-diameter-nm", "200"]) == 2
    assert "--pixel-size-nm" in capsys.readouterr().err


def test_few_beads_say_the_model_is_shift_invariant(tmp_path, capsys):
    assert main(["simulate", "-o", str(tmp_path / "two.tif"), "--shape", "256", "256",
                 "--beads", "2", "--seed", "3"]) == 0
    assert main(["estimate", str(tmp_path / "two.tif"), "-o", str(tmp_path / "m.npz"),
                 "-q"]) == 0
    out = capsys.readouterr().out
    assert "The model is shift-invariant (one PSF for the whole field)" in out
    assert "2 usable beads, fewer than 5: one PSF: too few beads to map the field" in out
    assert out.rstrip().endswith("one PSF: too few beads to map the field")  # no corners


def test_deblur_with_a_model_writes_the_parts_and_names_saturated_pixels(workdir, capsys):
    d = workdir
    if not (d / "model.npz").exists():
        radius = json.loads(tifffile.TiffFile(d / "beads.tif").imagej_metadata["Info"])[
            "psf_radius"]
        assert main(["estimate", str(d / "beads.tif"), "-o", str(d / "model.npz"),
                     "--psf-radius", str(radius), "-q"]) == 0
    img = tifffile.imread(d / "beads.tif").astype(float)
    # a 16-bit camera whose brightest pixels clip: the top 0.01 % at 65535
    img16 = np.clip(img * 65535 / np.percentile(img, 99.99), 0, 65535).astype(np.uint16)
    tifffile.imwrite(d / "clipped.tif", img16)
    capsys.readouterr()
    assert main(["deblur", str(d / "clipped.tif"), "--model", str(d / "model.npz"),
                 "-o", str(d / "out.tif"), "--parts", "--max-iter", "40", "-q"]) == 0
    out = capsys.readouterr().out
    n = int((img16 == 65535).sum())
    assert n > 0 and f"{n} saturated pixels (>= 65535)" in out
    for name in ("out.tif", "out.sparse.tif", "out.smooth.tif"):
        part = tifffile.imread(d / name)
        assert part.shape == (384, 384) and np.isfinite(part).all() and part.min() >= 0
