"""Memory before allocation: every door whose arrays grow with what the user gives
estimates them first and refuses, in one line naming the size and the parameter, what
the machine cannot hold, before any work.

The machine's available memory is made small here (``available_memory`` returns 1 MiB),
so that the ordinary inputs below each need more than it holds; with the real figure
the same calls run (the rest of the suite)."""

from __future__ import annotations

import contextlib
import io
import re

import numpy as np
import pytest
import tifffile

import napari_psfspace as ps
from napari_psfspace.cli import main
from napari_psfspace.core.common import validate

SMALL = 2**20
NEEDS = re.compile(r"needs about [0-9.e+-]+ GiB of memory; this machine has 0.000977 GiB "
                   r"available")

IMAGE = ps.simulate_beads((256, 256), 6, seed=2, min_separation=30, border=16)[0]
rng = np.random.default_rng(0)
OP = ps.ProductConvolution(rng.random((4, 15, 15)), 0.2 + rng.random((4, 3, 3)),
                           shape=(256, 256), grid=(np.linspace(0, 255, 3),) * 2)
OP3 = ps.ProductConvolution3D(rng.random((1, 5, 9, 9)), np.ones((1, 2, 2)),
                              shape=(24, 128, 128), plane=2,
                              grid=(np.array([0.0, 127]), np.array([0.0, 127])))
STACK = rng.poisson(100, (24, 128, 128)).astype(np.float32)

DOORS = {
    "detect_beads": (lambda: ps.detect_beads(IMAGE, 3), "`image` of 256 x 256"),
    "estimate_operator": (lambda: ps.estimate_operator(IMAGE, psf_radius=4),
                          "`image` of 256 x 256"),
    "diagnose": (lambda: ps.diagnose(IMAGE, psf_radius=4), "`image` of 256 x 256"),
    "deblur": (lambda: ps.deblur(IMAGE, OP, max_iter=2), "`image` of 256 x 256"),
    "apply": (lambda: OP.apply(IMAGE), "`u` through the operator (4 kernels"),
    "adjoint": (lambda: OP.adjoint(IMAGE), "`v` through the operator (4 kernels"),
    "estimate_operator_3d": (lambda: ps.estimate_operator_3d(STACK, psf_radius=3),
                             "`stack` of 24 x 128 x 128"),
    "deblur_3d": (lambda: ps.deblur_3d(STACK, OP3, max_iter=1), "`stack` of 24 x 128 x 128"),
    "richardson_lucy_3d": (lambda: ps.richardson_lucy_3d(STACK, OP3, n_iter=1),
                           "on 24 x 128 x 128 voxels"),
    "estimate_family": (lambda: ps.estimate_family([IMAGE, IMAGE], psf_radius=4),
                        "`image` of 256 x 256"),
    "simulate_beads": (lambda: ps.simulate_beads((512, 512), 3), "`shape` (512, 512)"),
    "simulate_focus_series": (lambda: ps.simulate_focus_series((512, 512), 3),
                              "of 512 x 512"),
    "simulate_psf": (lambda: ps.simulate_psf({4: 0.1}, size=301), "`size` 301"),
}


@pytest.fixture
def small_machine(monkeypatch):
    monkeypatch.setattr(validate, "available_memory", lambda: SMALL)


@pytest.mark.parametrize("door", sorted(DOORS))
def test_a_door_refuses_what_the_machine_cannot_hold(small_machine, door):
    call, names = DOORS[door]
    with pytest.raises(ValueError) as info:
        call()
    msg = str(info.value)
    assert "\n" not in msg and NEEDS.search(msg) and names in msg, msg


def test_a_tiff_too_large_for_the_machine_is_not_read(small_machine, tmp_path):
    """The command line: the file's decoded size is checked before its pixels are read;
    exit 2, one line naming the file, nothing written."""
    tifffile.imwrite(tmp_path / "big.tif", np.zeros((2048, 2048), np.uint16))
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(["estimate", str(tmp_path / "big.tif"), "-o", str(tmp_path / "m.npz"),
                   "--psf-radius", "4"])
    assert rc == 2, err.getvalue()
    line = err.getvalue().strip()
    assert "\n" not in line and "big.tif" in line and "2048 x 2048 uint16" in line, line
    assert NEEDS.search(line), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.tif"]


def test_the_operators_estimate_bounds_what_it_holds():
    """The estimate an application is refused by covers what one allocates: traced
    allocations of a first ``apply`` (maps and spectra made then) stay under it."""
    import tracemalloc

    op = ps.ProductConvolution(rng.random((4, 15, 15)), 0.2 + rng.random((4, 3, 3)),
                               shape=(256, 256), grid=(np.linspace(0, 255, 3),) * 2)
    u = IMAGE.astype(np.float32)
    tracemalloc.start()
    try:
        op.apply(u, workers=1)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= op.working_bytes(np.float32), (peak, op.working_bytes(np.float32))
