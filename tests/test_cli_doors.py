"""Every door of the command line checks before it works.

A table of bad invocations, tried as a new user would: each exits with status 2 and one
line that names the option or the file and what is wrong, with no traceback, and before
any long work (the computations are replaced by a trap that fails the test if it is
reached) and without writing the output. Damaged model and family files are one-line
errors in the API too.
"""

import os
import shutil
import stat

import numpy as np
import pytest
import tifffile

import napari_psfspace as ps
from napari_psfspace.cli import main
from napari_psfspace.core.common.device import gpu_status
from napari_psfspace.core.family import OperatorFamily
from napari_psfspace.core.model.cone import Cone


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("doors")
    image, truth = ps.simulate_beads((192, 192), 16, seed=3)
    tifffile.imwrite(d / "beads.tif", image)
    tifffile.imwrite(d / "beads2.tif", image)
    tifffile.imwrite(d / "stack.tif", np.stack([image] * 3), photometric="minisblack")
    tifffile.imwrite(d / "rgb.tif", np.stack([image.astype(np.uint8)] * 3, axis=-1),
                     photometric="rgb")
    tifffile.imwrite(d / "complex.tif", image.astype(np.complex64))
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius, holdout=None)
    op.save(d / "model.npz")
    raw = (d / "model.npz").read_bytes()
    (d / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    flipped = bytearray(raw)
    flipped[len(raw) // 3] ^= 0xFF  # inside an entry: its checksum fails
    (d / "flip.npz").write_bytes(bytes(flipped))
    (d / "text.npz").write_text("row,column\n1,2\n")
    n_i = op.basis.shape[0]
    gy, gx = op.grid
    space = np.ones((1, len(gy), len(gx))) / np.sqrt(len(gy) * len(gx))
    family = OperatorFamily(op.basis, space, op.grid, op.image_shape, np.ones((2, n_i, 1)),
                              # its generators: the model's PSFs at its nodes
                              Cone(op.coefficients.reshape(n_i, -1).T),
                              metadata={"psf_radius": truth.psf_radius})
    family.save(d / "family.npz")
    raw = (d / "family.npz").read_bytes()
    (d / "family_trunc.npz").write_bytes(raw[: len(raw) - 100])
    shutil.copy(d / "beads.tif", d / "positions.csv")  # a TIFF given as --beads
    (d / "ok.csv").write_text("10,10\n50,60\n")
    from napari_psfspace.core.volume import ProductConvolution3D

    ProductConvolution3D(np.ones((1, 3, 7, 7)), np.ones((1, 1, 1)), shape=(3, 192, 192),
                         grid=(np.zeros(1), np.zeros(1)), plane=1).save(d / "model3d.npz")
    ro = d / "readonly"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
    yield d
    ro.chmod(stat.S_IRWXU)


#: (arguments with {d} for the folder, what the one line must say, the output it must not
#: write). Each case is a door a user walked into.
CASES = [
    # outputs, checked before the work
    ("estimate {d}/beads.tif -o {d}/nofolder/m.npz --psf-radius 5", "does not exist", None),
    ("estimate {d}/beads.tif -o {d} --psf-radius 5", "-o {d}: is a folder", None),
    ("estimate {d}/beads.tif -o {d}/readonly/m.npz --psf-radius 5", "not writable", None),
    ("diagnose {d}/beads.tif --report {d}/beads2.tif --psf-radius 5", "--report", None),
    ("diagnose {d}/beads.tif --report {d}/r --model {d} --psf-radius 5", "--model", "r"),
    ("learn {d}/stack.tif --slices 0:3 -o {d} --psf-radius 5", "is a folder", None),
    ("deblur {d}/beads.tif --model {d}/model.npz -o {d}/readonly/x.tif", "not writable", None),
    ("apply {d}/model.npz {d}/beads.tif -o {d}/nofolder/x.tif", "does not exist", None),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/readonly/x.tif", "not writable",
     None),
    ("deblur3d {d}/stack.tif --model {d}/nomodel.npz -o {d}/x3.tif", "--model", "x3.tif"),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/x3.tif --rtol -1", "--rtol",
     "x3.tif"),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/x3.tif --scheduler tcp://a:1",
     "--tile", "x3.tif"),
    ("deblur3d {d}/stack.tif --model {d}/model.npz -o {d}/x3.tif", "3D model", "x3.tif"),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/x3.zarr", "--memory", "x3.zarr"),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/x3.zarr --memory lots",
     "--memory", "x3.zarr"),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/x3.zarr --memory 1GB --resume",
     "nothing to resume", "x3.zarr"),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/nofolder/x3.zarr --memory 1GB",
     "does not exist", None),
    ("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/x3.zarr --memory 1MB",
     "`memory` must be at least", "x3.zarr"),
    ("simulate -o {d}/nofolder/x.tif", "does not exist", None),
    ("demo --out {d}/beads.tif", "--out", None),
    # inputs: missing, damaged, of another kind
    ("estimate {d}/missing.tif -o {d}/m.npz --psf-radius 5", "missing.tif: no such file",
     "m.npz"),
    ("estimate {d}/text.npz -o {d}/m.npz --psf-radius 5", "not a readable TIFF", "m.npz"),
    ("estimate {d}/rgb.tif -o {d}/m.npz --psf-radius 5", "colour image", "m.npz"),
    ("apply {d}/model.npz {d}/complex.tif -o {d}/x.tif", "complex", "x.tif"),
    ("psf {d}/trunc.npz --at 5 5 -o {d}/p.tif", "trunc.npz': damaged model file", "p.tif"),
    ("psf {d}/flip.npz --at 5 5 -o {d}/p.tif", "flip.npz': damaged model file", "p.tif"),
    ("psf {d}/text.npz --at 5 5 -o {d}/p.tif", "not an .npz archive", "p.tif"),
    ("apply {d}/trunc.npz {d}/beads.tif -o {d}/x.tif", "damaged model file", "x.tif"),
    ("deblur {d}/beads.tif --model {d}/flip.npz -o {d}/x.tif", "damaged model file", "x.tif"),
    ("deblur {d}/beads.tif --family {d}/missing.npz -o {d}/x.tif",
     "--family {d}/missing.npz: no such file", "x.tif"),
    ("deblur {d}/beads.tif --family {d}/family_trunc.npz -o {d}/x.tif",
     "damaged family file", "x.tif"),
    ("deblur {d}/beads.tif --family {d}/family.npz --beads {d}/positions.csv -o {d}/x.tif",
     "not a CSV text file", "x.tif"),
    ("deblur {d}/beads.tif --model {d}/model.npz --beads {d}/ok.csv -o {d}/x.tif",
     "--beads identifies", "x.tif"),
    ("psf {d}/family.npz --image 99 --at 5 5 -o {d}/p.tif", "--image 99 is out of range",
     "p.tif"),
    # values: named, never clipped or ignored
    ("estimate {d}/stack.tif --slice 99 -o {d}/m.npz --psf-radius 5", "--slice 99", "m.npz"),
    ("estimate {d}/stack.tif --slice -1 -o {d}/m.npz --psf-radius 5", "--slice", "m.npz"),
    ("estimate {d}/beads.tif --slice 2 -o {d}/m.npz --psf-radius 5", "one 2-D image", "m.npz"),
    ("estimate {d}/beads.tif -o {d}/m.npz --n-psf banana", "--n-psf", "m.npz"),
    ("estimate {d}/beads.tif -o {d}/m.npz --psf-radius nan", "--psf-radius", "m.npz"),
    ("estimate {d}/beads.tif -o {d}/m.npz --holdout 2", "--holdout", "m.npz"),
    ("estimate {d}/beads.tif -o {d}/m.npz --threshold -1", "--threshold", "m.npz"),
    ("diagnose {d}/beads.tif --report {d}/r --gain nan", "--gain", "r"),
    ("learn {d}/stack.tif --slices 5:7000 -o {d}/f.npz --psf-radius 5", "--slices 5:7000",
     "f.npz"),
    ("learn {d}/beads.tif {d}/beads2.tif --slices 0:2 -o {d}/f.npz", "--slices", "f.npz"),
    ("learn {d}/stack.tif -o {d}/f.npz --n-space 1e9", "--n-space", "f.npz"),
    # a radius too large for the images (once a MemoryError in the bound on --n-space)
    ("learn {d}/stack.tif -o {d}/f.npz --psf-radius 1e12", "--psf-radius: the PSF radius",
     "f.npz"),
    ("learn {d}/stack.tif -o {d}/f.npz --psf-radius 5 --n-space 1000000000",
     "--n-space 1000000000 is more", "f.npz"),
    ("psf {d}/model.npz --at nan 5 -o {d}/p.tif", "--at", "p.tif"),
    ("deblur {d}/beads.tif --model {d}/model.npz -o {d}/x.tif --max-iter 2.5", "--max-iter",
     "x.tif"),
    ("simulate -o {d}/x.tif --beads 0", "--beads", "x.tif"),
]
# the GPU: named before any work; without CuPy or a device, the extra that installs it
CASES.append(("deblur {d}/beads.tif --model {d}/model.npz -o {d}/x.tif --device cuda",
              "--device", "x.tif"))
if not gpu_status()[0]:
    for method in ("rl", "sparse"):
        CASES.append((f"deblur3d {{d}}/stack.tif --model {{d}}/model3d.npz -o {{d}}/x3.tif "
                      f"--device gpu --method {method}", "napari-psfspace[gpu]", "x3.tif"))
    CASES.append(("deblur {d}/beads.tif --model {d}/model.npz -o {d}/x.tif --device gpu",
                  "napari-psfspace[gpu]", "x.tif"))
    # tiles on a GPU are run where there is one; without, the same line before any work
    CASES.append(("deblur3d {d}/stack.tif --model {d}/model3d.npz -o {d}/x3.zarr --device "
                  "gpu --tile 64", "napari-psfspace[gpu]", "x3.zarr"))


@pytest.fixture
def trapped(monkeypatch):
    """Every long computation the command line starts fails the test if reached."""
    import napari_psfspace.core.diagnosis.loop as loop
    import napari_psfspace.core.family as subspace
    import napari_psfspace.core.model.estimate as estimate
    import napari_psfspace.core.restore as restore
    import napari_psfspace.core.simulation as simulation
    import napari_psfspace.core.volume.deconvolve3d as deconvolve3d
    import napari_psfspace.core.volume.fista3d as fista3d
    import napari_psfspace.core.volume.tiles3d as tiles3d
    import napari_psfspace.demo as demo

    def trap(*args, **kwargs):
        raise AssertionError("the long work started before the door was checked")

    for module, name in ((estimate, "iter_estimate"), (loop, "iter_diagnose"),
                         (subspace, "iter_estimate_family"), (restore, "iter_deblur"),
                         (restore, "identify_operator"), (simulation, "simulate_beads"),
                         (demo, "run_demo"), (deconvolve3d, "iter_richardson_lucy_3d"),
                         (fista3d, "iter_deblur_3d"), (tiles3d, "richardson_lucy_3d_tiled")):
        monkeypatch.setattr(module, name, trap)


@pytest.mark.parametrize("args, says, output", CASES, ids=[c[0].split()[0] + ":" + c[1][:24]
                                                           for c in CASES])
def test_a_bad_invocation_is_one_line_before_any_work(files, trapped, capsys, args, says,
                                                      output):
    d = str(files)
    code = main(args.format(d=d).split())
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert code == 2, err
    assert "\n" not in err and "Traceback" not in err, err
    assert says.format(d=d) in err, err
    if output:
        assert not (files / output).exists()


def test_a_dead_scheduler_is_named(files, trapped, capsys, monkeypatch):
    """A scheduler that does not answer: a one-line error naming --scheduler, after the
    timeout (shortened here), not a traceback."""
    pytest.importorskip("distributed")
    import napari_psfspace.cli.common as common

    monkeypatch.setattr(common, "SCHEDULER_TIMEOUT", "1s")
    code = main(["learn", str(files / "stack.tif"), "--slices", "0:3", "-o",
                 str(files / "f.npz"), "--psf-radius", "5", "--scheduler", "tcp://127.0.0.1:9"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--scheduler tcp://127.0.0.1:9" in err and "\n" not in err, err


def test_damaged_files_are_value_errors_in_the_api(files):
    """Any single altered byte of a model file: a ValueError naming the file, or the
    file loads (a byte the archive does not check); never another exception."""
    raw = (files / "model.npz").read_bytes()
    rng = np.random.default_rng(0)
    damaged = 0
    path = files / "fuzz.npz"
    for _ in range(150):
        data = bytearray(raw)
        data[int(rng.integers(len(data)))] ^= int(rng.integers(1, 256))
        path.write_bytes(bytes(data))
        try:
            ps.load_operator(path)
        except ValueError as exc:
            assert "fuzz.npz" in str(exc)
            damaged += 1
    assert damaged >= 140  # nearly every byte is under a checksum
    with pytest.raises(ValueError, match="damaged family file"):
        ps.load_family(files / "family_trunc.npz")
    with pytest.raises(FileNotFoundError):
        ps.load_family(files / "missing.npz")


def test_the_api_names_the_wrong_argument(files):
    image = tifffile.imread(files / "beads.tif")
    op = ps.load_operator(files / "model.npz")
    family = ps.load_family(files / "family.npz")
    with pytest.raises(TypeError, match="`family` must be an OperatorFamily"):
        ps.identify_operator(image, op)
    with pytest.raises(TypeError, match="`operator` must be a ProductConvolution"):
        ps.deblur(image, family)
    for kwargs, name in (({"max_iter": 2.5}, "max_iter"), ({"grid_step": 1e9}, "grid_step"),
                         ({"saturation": float("nan")}, "saturation")):
        with pytest.raises(ValueError, match=f"`{name}`"):
            ps.deblur(image, op, **kwargs)
    with pytest.raises(ValueError, match="`k`"):
        family.operator(1.5)
    with pytest.raises(ValueError, match="`k`"):
        family.operator(2)


def test_the_readonly_folder_is_refused_even_to_root(files):
    """The check reads the permission bits (root may write anywhere, a user's read-only
    data folder must still be refused)."""
    assert not os.stat(files / "readonly").st_mode & stat.S_IWUSR
