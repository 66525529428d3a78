"""The ten worst doors a fuzz written from outside found: each refused with one line
naming what is wrong (exit 2 on the command line) before any work, or a correct result."""

import numpy as np
import pytest
import tifffile

import napari_psfspace as ps
from napari_psfspace.cli import main
from napari_psfspace.core.model.operator import ProductConvolution
from napari_psfspace.core.volume.operator3d import ProductConvolution3D


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("worst")
    image, _ = ps.simulate_beads((128, 128), 4, seed=1)
    tifffile.imwrite(d / "sim.tif", image)
    tifffile.imwrite(d / "zeros.tif", np.zeros_like(image))
    tifffile.imwrite(d / "negated.tif", -image.astype(np.float32))
    (d / "header.tif").write_bytes((d / "sim.tif").read_bytes()[:8])  # a header alone
    rng = np.random.default_rng(0)
    grid = (np.linspace(0, 127, 3), np.linspace(0, 127, 3))
    basis, coef = rng.random((2, 9, 9)), 0.1 + rng.random((2, 3, 3))
    ProductConvolution(basis, coef, shape=(128, 128), grid=grid).save(d / "m.npz")
    ProductConvolution(basis, -coef, shape=(128, 128), grid=grid).save(d / "neg.npz")
    ProductConvolution(0 * basis, coef, shape=(128, 128), grid=grid).save(d / "zero.npz")
    ProductConvolution(basis, coef, shape=(200000, 200000), grid=grid).save(d / "big.npz")
    op3 = ProductConvolution3D(rng.random((1, 3, 7, 7)), np.ones((1, 2, 2)),
                               shape=(4, 64, 64), plane=1,
                               grid=(np.array([0.0, 63]), np.array([0.0, 63])))
    op3.save(d / "m3.npz")
    stack = rng.poisson(50, op3.image_shape).astype(np.float32)
    tifffile.imwrite(d / "stack.tif", stack, imagej=True)
    tifffile.imwrite(d / "negstack.tif", -stack, imagej=True)
    return d


def _refused(capsys, argv, says, d):
    before = sorted(p.name for p in d.iterdir())
    capsys.readouterr()
    assert main([a.format(d=d) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err, err
    assert sorted(p.name for p in d.iterdir()) == before  # nothing written


@pytest.mark.parametrize("argv, says", [
    # 1: an image of zeros; 6: a negated image and stack, a background above the data
    ("deblur {d}/zeros.tif --model {d}/m.npz -o {d}/o.tif", "holds no positive value"),
    ("deblur {d}/negated.tif --model {d}/m.npz -o {d}/o.tif", "holds no positive value"),
    ("deblur3d {d}/negstack.tif --model {d}/m3.npz -o {d}/o.tif", "holds no positive value"),
    ("deblur3d {d}/stack.tif --model {d}/m3.npz -o {d}/o.tif --background 1e30",
     "at or above the data's largest value"),
    ("deblur3d {d}/stack.tif --model {d}/m3.npz -o {d}/o.zarr --tile 32 --background 1e30",
     "at or above the data's largest value"),
    # 2: a TIFF cut after its header
    ("estimate {d}/header.tif -o {d}/o.npz --psf-radius 5", "it holds no image"),
    ("apply {d}/m.npz {d}/header.tif -o {d}/o.tif", "it holds no image"),
    # 3: an empty output folder
    ("demo --out ", "--out: an empty path"),
    # 4: an output that is another output, or an input
    ("simulate -o {d}/s.tif --truth-grid {d}/s.tif", "-o and --truth-grid are the same"),
    ("apply {d}/m.npz {d}/sim.tif -o {d}/sim.tif", "is the input IMAGE"),
    ("deblur3d {d}/stack.tif --model {d}/m3.npz -o {d}/stack.tif", "is the input STACK"),
    # 5, 7: a model that is no blur, or whose shape is not its grid's
    ("apply {d}/neg.npz {d}/sim.tif -o {d}/o.tif", "sums to -"),
    ("apply {d}/zero.npz {d}/sim.tif -o {d}/o.tif", "sums to 0"),
    ("psf {d}/zero.npz --at 10 10 -o {d}/o.tif", "sums to 0"),
    ("psf {d}/big.npz --at 150000 10 -o {d}/o.tif", "does not match its grid"),
])
def test_the_worst_command_lines_are_refused_in_one_line(folder, capsys, argv, says):
    _refused(capsys, argv.split(" "), says, folder)


@pytest.mark.parametrize("call, says", [
    # 8: camera values that make no image
    (lambda: ps.simulate_beads((128, 128), 4, gain=0), "`gain`"),
    (lambda: ps.simulate_beads((128, 128), 4, gain=np.nan), "`gain`"),
    (lambda: ps.simulate_beads((128, 128), 4, offset=np.nan), "`offset`"),
    (lambda: ps.simulate_beads((128, 128), 4, read_noise=np.nan), "`read_noise`"),
    (lambda: ps.simulate_beads((128, 128), 4, dtype=np.int8), "`dtype`"),
    # 9: a saturation level no camera has
    (lambda: ps.detect_beads(ps.simulate_beads((128, 128), 4)[0], 6, saturation=-1),
     "`saturation`"),
    # 10: a grid step of zero, a Zernike index beyond any pupil
    (lambda: ps.estimate_family([np.ones((64, 64))] * 2, psf_radius=5, grid_step=0),
     "`grid_step`"),
    (lambda: ps.simulate_psf({999: 1.0}), "Noll index 999"),
    # memory before allocation: a PSF window no machine holds
    (lambda: ps.simulate_psf(size=100001), "`size` 100001.*GiB of memory"),
])
def test_the_worst_api_calls_name_their_argument(monkeypatch, call, says):
    from napari_psfspace.core.common import validate

    # the memory a machine of 16 GiB has free: the refusal does not depend on this one's
    monkeypatch.setattr(validate, "available_memory", lambda: 16 * 2**30)
    with pytest.raises(ValueError, match=says):
        call()
