"""compress_operator: the fewest kernels for a PSF field, to a stated error."""

from __future__ import annotations

import numpy as np
import pytest

from napari_psfspace.core.model.compress import compress_operator
from napari_psfspace.core.model.operator import ProductConvolution
from napari_psfspace.core.restore.deconvolve import COMPRESSION, deblur
from tolerances import U64, gamma

SHAPE = (96, 112)
HALF = 7


def _gaussian(sy, sx):
    yy, xx = np.mgrid[-HALF:HALF + 1, -HALF:HALF + 1]
    g = np.exp(-yy ** 2 / (2 * sy ** 2) - xx ** 2 / (2 * sx ** 2))
    return g / g.sum()


def _node_field(n=4):
    """One kernel per grid node (n x n): a Gaussian whose widths drift over the field,
    the representation whose kernels outnumber the field's degrees of freedom."""
    gy = np.linspace(0, SHAPE[0] - 1, n)
    gx = np.linspace(0, SHAPE[1] - 1, n)
    basis, coef = [], np.zeros((n * n, n, n))
    for i, y in enumerate(gy):
        for j, x in enumerate(gx):
            basis.append(_gaussian(1.5 + y / SHAPE[0], 1.5 + 0.8 * x / SHAPE[1]))
            coef[i * n + j, i, j] = 1.0
    return ProductConvolution(np.array(basis), coef, shape=SHAPE, grid=(gy, gx),
                              metadata={"identification": {"model_error": 0.2}})


def _points_image(op, seed):
    """30 points of 800 photons seen through ``op`` on a background of 50, Poisson."""
    rng = np.random.default_rng(seed)
    truth = np.zeros(SHAPE, np.float32)
    truth[rng.integers(10, 86, 30), rng.integers(10, 102, 30)] = 800
    return rng.poisson(op.apply(truth) + 50).astype(np.float32)


def _qr_svd_bound(rows, cols):
    """Householder QR and the SVD are backward stable: within ``gamma(c m n)`` of the
    matrix's norm (Higham, Thm 19.4), c a small constant (10 here)."""
    return gamma(10 * rows * cols, U64)


def test_an_exactly_low_rank_field_keeps_its_rank_and_its_psfs():
    rng = np.random.default_rng(0)
    base = np.array([_gaussian(1.5, 1.5), _gaussian(2.5, 1.8), _gaussian(1.8, 3.0)])
    mix = rng.normal(size=(3, 3))
    basis = np.concatenate([base, np.tensordot(mix, base, axes=1)])  # 6 kernels, rank 3
    coef = rng.uniform(0, 1, (6, 3, 4))
    op = ProductConvolution(basis, coef, shape=SHAPE,
                            grid=(np.linspace(0, 95, 3), np.linspace(0, 111, 4)))
    small = compress_operator(op, 0.0)
    assert small.n_psf == 3
    assert small.metadata["compressed"]["from"] == 6
    bound = _qr_svd_bound(coef[0].size, basis[0].size) * np.abs(basis).sum() * 6
    for y, x in rng.uniform(0, 95, (20, 2)):
        a, b = op.psf_at(y, x), small.psf_at(y, x)
        assert np.linalg.norm(a - b) <= bound * max(np.abs(coef).sum(), 1)


def test_the_error_stays_within_rtol_at_every_node_and_no_kernel_is_spare():
    op = _node_field()
    rtol = 0.02
    small = compress_operator(op, rtol)
    info = small.metadata["compressed"]
    assert small.n_psf < op.n_psf
    assert info["error"] <= rtol
    assert small.metadata["identification"] == op.metadata["identification"]
    gy, gx = op.grid
    for y in gy:
        for x in gx:
            a, b = op.psf_at(y, x), small.psf_at(y, x)
            assert np.linalg.norm(a - b) <= (rtol + 1e-9) * np.linalg.norm(a)
    # one kernel fewer misses the bound somewhere: asking for less error takes more
    tighter = compress_operator(op, 0.999 * info["error"])
    assert tighter.n_psf > small.n_psf


def test_full_resolution_maps_compress_like_a_grid():
    op = _node_field()
    maps = op.coefficient_maps(np.float64)
    full = ProductConvolution(op.basis, maps)
    small = compress_operator(full, 0.02)
    assert small.is_full_resolution and small.n_psf < full.n_psf
    x = np.random.default_rng(1).random(SHAPE)
    rel = np.linalg.norm(small.apply(x) - full.apply(x)) / np.linalg.norm(full.apply(x))
    assert rel <= 0.02


def test_bad_rtol_is_named():
    with pytest.raises(ValueError, match="`rtol`"):
        compress_operator(_node_field(), -0.1)
    with pytest.raises(ValueError, match="`rtol`"):
        compress_operator(_node_field(), float("nan"))


def test_deblur_compresses_to_a_fraction_of_the_operators_own_error():
    op = _node_field()
    image = _points_image(op, seed=2)
    res = deblur(image, op, max_iter=30)
    assert res.parameters["compression"] == pytest.approx(COMPRESSION * 0.2)
    assert res.parameters["kernels"][0] == 16 > res.parameters["kernels"][1]
    exact = deblur(image, op, max_iter=30, compression=0)
    assert exact.parameters["kernels"] == [16, 16]
    with pytest.raises(ValueError, match="`compression`"):
        deblur(image, op, compression=-1.0)


def test_a_coarser_search_operator_does_not_change_where_the_deblur_ends(monkeypatch):
    """FISTA's search for the support runs on fewer kernels (``SEARCH_COMPRESSION``);
    the sweeps, the optimality check and the FISTA after them on the exact operator, so
    the result is the exact problem's: its objective, under the exact operator, is that
    of a run searching with the exact operator too."""
    import napari_psfspace.core.restore.deconvolve as dec
    op = _node_field()
    image = _points_image(op, seed=3)
    coarse = deblur(image, op, compression=0)
    monkeypatch.setattr(dec, "SEARCH_COMPRESSION", 0.0)
    exact = deblur(image, op, compression=0)
    assert coarse.parameters["search_kernels"] < 16 == exact.parameters["search_kernels"]
    assert coarse.parameters["polish_sweeps"] > 0 and coarse.converged and exact.converged

    gmap, _, _ = dec.default_weights(image, op, coarse.parameters["grid_step"],
                                     model_error=0.2)

    def objective(res):
        r = image.astype(np.float64) - op.apply(res.image)
        return 0.5 * float(np.vdot(r, r)) + float(np.vdot(gmap, res.sparse))

    a, b = objective(coarse), objective(exact)
    # both stop by the same relative rule (1e-4 over 10 iterations or sweeps), which
    # bounds the fall still to come only loosely: 10 times it either way
    assert abs(a - b) <= 1e-3 * b, (a, b)
