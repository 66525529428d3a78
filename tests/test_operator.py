"""Tests for napari_psfspace.core.model.operator (product-convolution operator)."""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np
import pytest
from scipy.signal import fftconvolve

from napari_psfspace.core.common import atomic as _atomic
from napari_psfspace.core.model.operator import ProductConvolution, load_operator
from napari_psfspace.core.model.operator_file import FORMAT_NAME, FORMAT_VERSION
from tolerances import U64, abs_dot, gamma, product_convolution_errors

SEED = 20240611


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(SEED)


def _gaussian_basis(n_psf: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Positive Gaussian-like PSFs of different widths plus a little noise (I, P, P)."""
    c = size // 2
    yy, xx = np.mgrid[-c : c + 1, -c : c + 1]
    out = []
    for i in range(n_psf):
        s = 0.8 + 0.5 * i
        g = np.exp(-(yy**2 + xx**2) / (2 * s**2))
        out.append(g / g.sum() + 1e-3 * rng.random((size, size)))
    return np.array(out)


def _coarse_model(rng, shape=(48, 37), n_psf=3, size=7, nodes=(4, 3)) -> ProductConvolution:
    gy = np.linspace(-3.0, shape[0] + 2.0, nodes[0])  # nodes partly outside the image
    gx = np.sort(rng.uniform(0, shape[1], nodes[1]))
    coef = rng.standard_normal((n_psf, *nodes))
    return ProductConvolution(
        rng.standard_normal((n_psf, size, size)), coef, shape=shape, grid=(gy, gx)
    )


def _full_model(rng, shape=(41, 50), n_psf=3, size=9) -> ProductConvolution:
    return ProductConvolution(
        rng.standard_normal((n_psf, size, size)), rng.standard_normal((n_psf, *shape))
    )


# --------------------------------------------------------------------------- adjoint
@pytest.mark.parametrize("kind", ["full", "coarse"])
def test_dot_test_float64(rng, kind):
    op = _full_model(rng) if kind == "full" else _coarse_model(rng)
    u = rng.standard_normal(op.image_shape)
    v = rng.standard_normal(op.image_shape)
    lhs = np.vdot(op.apply(u), v)
    rhs = np.vdot(u, op.adjoint(v))
    assert abs(lhs - rhs) / abs(lhs) < 1e-10


@pytest.mark.parametrize("kind", ["full", "coarse"])
def test_dot_test_float32(rng, kind):
    op = _full_model(rng) if kind == "full" else _coarse_model(rng)
    u = rng.standard_normal(op.image_shape).astype(np.float32)
    v = rng.standard_normal(op.image_shape).astype(np.float32)
    hu, htv = op.apply(u), op.adjoint(v)
    assert hu.dtype == np.float32 and htv.dtype == np.float32
    lhs = np.vdot(hu.astype(np.float64), v.astype(np.float64))
    rhs = np.vdot(u.astype(np.float64), htv.astype(np.float64))
    # |<dHu, v>| <= ||dHu|| ||v|| and |<u, dH^T v>| <= ||u|| ||dH^T v||, each error
    # bounded from the sizes it sums (tests/tolerances.py); the inner products in float64
    err_hu, err_htv = product_convolution_errors(op, u, v)
    bound = (err_hu * np.linalg.norm(v) + np.linalg.norm(u) * err_htv
             + gamma(2 * u.size, U64) * (abs_dot(hu, v) + abs_dot(u, htv)))
    assert abs(lhs - rhs) <= bound
    assert bound < 0.1 * abs(lhs)  # can fail: a wrong adjoint is off by about |lhs|



def test_linear_operator_wraps_apply_and_adjoint(rng):
    op = _coarse_model(rng)
    lin = op.as_linear_operator()
    n = op.image_shape[0] * op.image_shape[1]
    assert lin.shape == (n, n)
    u = rng.standard_normal(op.image_shape)
    err_mv = np.max(np.abs(lin.matvec(u.ravel()) - op.apply(u).ravel()))
    err_rmv = np.max(np.abs(lin.rmatvec(u.ravel()) - op.adjoint(u).ravel()))
    assert err_mv < 1e-14 * np.abs(op.apply(u)).max() + 1e-300
    assert err_rmv < 1e-14 * np.abs(op.adjoint(u)).max() + 1e-300


@pytest.mark.parametrize("n_psf", [1, 3])
def test_data_gradient_is_the_adjoint_of_the_residual(rng, n_psf):
    # 300 rows: the element-wise steps run split over threads (by_rows: >= 256 rows)
    op = _full_model(rng, shape=(300, 270), n_psf=n_psf)
    u = rng.standard_normal(op.image_shape)
    y = rng.standard_normal(op.image_shape)
    r = op.apply(u, workers=1) - y
    g, value = op.data_gradient(u, y, workers=2)
    np.testing.assert_allclose(g, op.adjoint(r, workers=1), rtol=0,
                               atol=1e-12 * np.abs(g).max())
    assert value == pytest.approx(float(np.vdot(r, r)), rel=1e-12)
    # threads change nothing (float64: the same products in the same order)
    np.testing.assert_array_equal(op.apply(u, workers=2), op.apply(u, workers=1))
    # censored pixels (saturated: y only a lower bound) count only where H u < y
    cens = np.nonzero(rng.random(op.image_shape) < 0.05)
    rc = r.copy()
    rc[cens] = np.minimum(rc[cens], 0)
    g, value = op.data_gradient(u, y, censored=cens, workers=2)
    np.testing.assert_allclose(g, op.adjoint(rc, workers=1), rtol=0,
                               atol=1e-12 * np.abs(g).max())
    assert value == pytest.approx(float(np.vdot(rc, rc)), rel=1e-12)
    with pytest.raises(ValueError, match="`y` of shape"):
        op.data_gradient(u, y[:-1])


# --------------------------------------------------------------------------- apply
def test_stationary_limit_matches_fftconvolve(rng):
    """Constant coefficients (1x1 grid): H u == fftconvolve(u, sum_i a_i h_i, 'same')."""
    shape, size = (35, 52), 11
    basis = rng.standard_normal((4, size, size))
    a = rng.standard_normal(4)
    op = ProductConvolution(
        basis, a[:, None, None], shape=shape, grid=(np.array([10.0]), np.array([3.0]))
    )
    # bright borders so that zero-boundary handling is exercised
    u = rng.standard_normal(shape)
    u[0, :] += 50.0
    u[:, -1] += 50.0
    ref = fftconvolve(u, np.tensordot(a, basis, axes=1), mode="same")
    rel = np.abs(op.apply(u) - ref).max() / np.abs(ref).max()
    assert rel < 1e-10
    border = np.zeros(shape, dtype=bool)
    border[: size // 2, :] = border[-(size // 2) :, :] = True
    border[:, : size // 2] = border[:, -(size // 2) :] = True
    rel_border = np.abs(op.apply(u) - ref)[border].max() / np.abs(ref).max()
    assert rel_border < 1e-10


def test_stationary_limit_constant_full_maps(rng):
    shape, size = (30, 27), 5
    basis = rng.standard_normal((2, size, size))
    a = np.array([0.7, -1.3])
    maps = np.broadcast_to(a[:, None, None], (2, *shape))
    op = ProductConvolution(basis, maps)
    u = rng.standard_normal(shape)
    ref = fftconvolve(u, np.tensordot(a, basis, axes=1), mode="same")
    assert np.abs(op.apply(u) - ref).max() / np.abs(ref).max() < 1e-10


def _dense_matrix(op: ProductConvolution) -> np.ndarray:
    """Explicit matrix: column z = PSF at z, sum_i alpha_i(z) h_i, placed centred at z."""
    H, W = op.image_shape
    P, c = op.psf_size, op.psf_size // 2
    maps = op.coefficient_maps(np.float64)
    mat = np.zeros((H * W, H * W))
    for y in range(H):
        for x in range(W):
            psf = np.tensordot(maps[:, y, x], op.basis, axes=1)  # (P, P)
            col = np.zeros((H + 2 * c, W + 2 * c))
            # output pixel (y + k, x + l) receives h[c + k, c + l] * u(y, x)
            col[y : y + P, x : x + P] = psf
            mat[:, y * W + x] = col[c : c + H, c : c + W].ravel()
    return mat


@pytest.mark.parametrize("kind", ["full", "coarse"])
def test_brute_force_dense_matrix(rng, kind):
    shape, size = (12, 10), 5
    basis = rng.standard_normal((3, size, size))
    if kind == "full":
        op = ProductConvolution(basis, rng.standard_normal((3, *shape)))
    else:
        op = ProductConvolution(
            basis,
            rng.standard_normal((3, 3, 2)),
            shape=shape,
            grid=(np.array([1.0, 5.5, 11.0]), np.array([2.0, 8.0])),
        )
    mat = _dense_matrix(op)
    u = rng.standard_normal(shape)
    ref = (mat @ u.ravel()).reshape(shape)
    assert np.abs(op.apply(u) - ref).max() / np.abs(ref).max() < 1e-12
    ref_adj = (mat.T @ u.ravel()).reshape(shape)
    assert np.abs(op.adjoint(u) - ref_adj).max() / np.abs(ref_adj).max() < 1e-12


def test_psf_larger_than_image(rng):
    """Padding must avoid wrap-around even when P > H, W (aliased kernel taps)."""
    basis = rng.standard_normal((2, 21, 21))
    op = ProductConvolution(basis, rng.standard_normal((2, 6, 5)))
    assert op.fft_shape()[0] < op.psf_size  # the case being tested
    mat = _dense_matrix(op)
    u = rng.standard_normal(op.image_shape)
    ref = (mat @ u.ravel()).reshape(op.image_shape)
    assert np.abs(op.apply(u) - ref).max() / np.abs(ref).max() < 1e-12
    ref_adj = (mat.T @ u.ravel()).reshape(op.image_shape)
    assert np.abs(op.adjoint(u) - ref_adj).max() / np.abs(ref_adj).max() < 1e-12


def test_dtypes(rng):
    op = _coarse_model(rng)
    u64 = rng.standard_normal(op.image_shape)
    out32 = op.apply(u64.astype(np.float32))
    assert out32.dtype == np.float32
    assert op.adjoint(u64.astype(np.float32)).dtype == np.float32
    assert op.apply(u64).dtype == np.float64
    u32 = u64.astype(np.float32)
    ref = op.apply(u32.astype(np.float64))
    # max |error| <= ||error||_2, bounded from the sizes summed (float64's is negligible)
    bound = product_convolution_errors(op, u32, u32)[0]
    assert np.abs(out32 - ref).max() <= bound < 0.01 * np.abs(ref).max()
    ui = rng.integers(0, 1000, op.image_shape).astype(np.uint16)
    out_i = op.apply(ui)
    assert out_i.dtype == np.float32
    ref_i = op.apply(ui.astype(np.float64))
    bound = product_convolution_errors(op, ui.astype(np.float64), ui.astype(np.float64))[0]
    assert np.abs(out_i - ref_i).max() <= bound < 0.01 * np.abs(ref_i).max()


# --------------------------------------------------------------------------- coefficients
def test_coefficients_at_matches_maps(rng):
    op = _coarse_model(rng)
    maps = op.coefficient_maps(np.float64)
    H, W = op.image_shape
    yy, xx = np.mgrid[0:H, 0:W]
    got = op.coefficients_at(yy.ravel(), xx.ravel())  # (N, I)
    assert got.shape == (H * W, op.n_psf)
    err = np.abs(got.T.reshape(op.n_psf, H, W) - maps).max()
    assert err < 1e-12
    assert op.coefficients_at(3, 4).shape == (op.n_psf,)
    maps32 = op.coefficient_maps()
    assert maps32.dtype == np.float32
    # bilinear: Ry @ A @ Rx.T, gy then gx terms per pixel, rounded to float32 at the end
    # (weights >= 0 summing to 1: |Ry| |A| |Rx^T| <= max |A|)
    gy, gx = (len(g) for g in op.grid)
    assert np.abs(maps32 - maps).max() <= gamma(gy + gx + 1) * np.abs(op.coefficients).max()


def test_coefficients_interpolation_is_bilinear_with_constant_extrapolation():
    basis = np.ones((1, 3, 3))
    coef = np.array([[[0.0, 2.0], [4.0, 10.0]]])
    op = ProductConvolution(basis, coef, shape=(20, 20), grid=([5.0, 15.0], [2.0, 12.0]))
    # centre of the cell: mean of the four corners
    assert abs(op.coefficients_at(10.0, 7.0)[0] - 4.0) < 1e-14
    # constant extrapolation beyond the nodes
    assert abs(op.coefficients_at(0.0, 0.0)[0] - 0.0) < 1e-14
    assert abs(op.coefficients_at(19.0, 19.0)[0] - 10.0) < 1e-14
    assert abs(op.coefficients_at(19.0, 7.0)[0] - 7.0) < 1e-14
    # a single node along an axis: constant along it
    op1 = ProductConvolution(basis, coef[:, :1, :], shape=(20, 20), grid=([5.0], [2.0, 12.0]))
    m = op1.coefficient_maps(np.float64)[0]
    assert np.abs(m - m[0]).max() < 1e-14


def test_psf_at_node(rng):
    size = 9
    basis = _gaussian_basis(3, size, rng)
    coef = 0.5 + rng.random((3, 3, 4))
    gy, gx = np.array([4.0, 20.0, 35.0]), np.array([0.0, 10.0, 20.0, 30.0])
    op = ProductConvolution(basis, coef, shape=(40, 31), grid=(gy, gx))
    psf = op.psf_at(gy[1], gx[2])
    ref = np.tensordot(coef[:, 1, 2], basis, axes=1)
    ref /= ref.sum()
    assert psf.shape == (size, size) and psf.dtype == np.float64
    assert np.abs(psf - ref).max() < 1e-14
    assert abs(psf.sum() - 1.0) < 1e-12


def test_psf_grid(rng):
    basis = _gaussian_basis(2, 7, rng)
    op = ProductConvolution(basis, 0.5 + rng.random((2, 30, 40)))
    ys, xs, psfs = op.psf_grid(3, 4)
    assert psfs.shape == (3, 4, 7, 7)
    assert ys[0] == 3 and ys[-1] == 26 and xs[0] == 3 and xs[-1] == 36
    err = np.abs(psfs[1, 2] - op.psf_at(ys[1], xs[2])).max()
    assert err < 1e-14
    ys1, xs1, _ = op.psf_grid(1, 1, margin=0)
    assert ys1[0] == 14.5 and xs1[0] == 19.5


def test_psf_at_non_positive_sum_raises():
    op = ProductConvolution(-np.ones((1, 3, 3)), np.ones((1, 5, 5)))
    with pytest.raises(ValueError, match="non-positive sum"):
        op.psf_at(2, 2)


# --------------------------------------------------------------------------- validation
def test_validation_messages(rng):
    good_b = rng.standard_normal((2, 5, 5))
    good_c = rng.standard_normal((2, 10, 12))
    with pytest.raises(ValueError, match=r"`basis` must have odd patch size, got \(2, 4, 4\)"):
        ProductConvolution(rng.standard_normal((2, 4, 4)), good_c)
    with pytest.raises(ValueError, match="`basis` must have square"):
        ProductConvolution(rng.standard_normal((2, 5, 7)), good_c)
    bad = good_b.copy()
    bad[1, 2, 2] = np.nan
    with pytest.raises(ValueError, match="`basis` contains 1 NaN"):
        ProductConvolution(bad, good_c)
    bad_c = good_c.copy()
    bad_c[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="`coefficients` contains"):
        ProductConvolution(good_b, bad_c)
    with pytest.raises(ValueError, match="`coefficients` must have I=2"):
        ProductConvolution(good_b, rng.standard_normal((3, 10, 12)))
    with pytest.raises(ValueError, match="`shape` .* does not match"):
        ProductConvolution(good_b, good_c, shape=(10, 13))
    with pytest.raises(ValueError, match="`shape` .* is required"):
        ProductConvolution(good_b, good_c[:, :2, :2], grid=([0, 5], [0, 5]))
    with pytest.raises(ValueError, match="strictly increasing"):
        ProductConvolution(good_b, good_c[:, :2, :2], shape=(10, 12), grid=([5, 0], [0, 5]))
    with pytest.raises(ValueError, match=r"`grid\[1\] \(grid_x\)` must have shape \(2,\)"):
        ProductConvolution(good_b, good_c[:, :2, :2], shape=(10, 12), grid=([0, 5], [0, 5, 9]))
    with pytest.raises(ValueError, match="`shape` must be two positive integers"):
        ProductConvolution(good_b, good_c[:, :2, :2], shape=(10.5, 12), grid=([0, 5], [0, 5]))
    with pytest.raises(ValueError, match="`metadata` must be JSON"):
        ProductConvolution(good_b, good_c, metadata={"x": object()})

    op = ProductConvolution(good_b, good_c)
    with pytest.raises(ValueError, match=r"estimated for an image of shape \(10, 12\), got"):
        op.apply(np.zeros((12, 10)))
    with pytest.raises(ValueError, match=r"estimated for an image of shape \(10, 12\), got"):
        op.adjoint(np.zeros((10, 11)))
    u = np.zeros((10, 12))
    u[3, 3] = np.nan
    with pytest.raises(ValueError, match="`u` contains NaN"):
        op.apply(u)
    with pytest.raises(ValueError, match="`v` contains NaN"):
        op.adjoint(u)
    u[3, 3] = -np.inf
    with pytest.raises(ValueError, match="`u` contains NaN or infinite"):
        op.apply(u)
    with pytest.raises(ValueError, match="`u` contains NaN or infinite"):
        op.apply(u.astype(np.float32))
    # a NaN where every coefficient map is zero must still be caught (0 * NaN = NaN)
    zero_maps = np.zeros_like(good_c)
    zero_maps[:, :, 6:] = 1.0
    op0 = ProductConvolution(good_b, zero_maps)
    u[:] = 0.0
    u[2, 1] = np.nan
    with pytest.raises(ValueError, match="`u` contains NaN"):
        op0.apply(u)
    with pytest.raises(ValueError, match="`u` must be real-valued"):
        op.apply(np.zeros((10, 12), dtype=complex))


def test_copy_keeps_behaviour(rng):
    import copy

    op = _coarse_model(rng)
    u = rng.standard_normal(op.image_shape)
    out = op.apply(u)
    op2 = copy.deepcopy(op)
    assert np.array_equal(op2.apply(u), out)


def test_properties_and_readonly(rng):
    op = _coarse_model(rng)
    assert op.n_psf == 3 and op.psf_size == 7 and op.image_shape == (48, 37)
    assert op.grid is not None and op.grid[0].shape == (4,)
    assert not op.basis.flags.writeable
    assert not op.coefficient_maps().flags.writeable
    assert "ProductConvolution(n_psf=3" in repr(op)
    full = _full_model(rng)
    assert full.grid is None and full.is_full_resolution


# --------------------------------------------------------------------------- I/O
def test_save_load_roundtrip(tmp_path, rng):
    meta = {"residual": np.float64(0.125), "n_beads": np.int64(17), "sizes": np.arange(3)}
    # files hold blurs (the loader checks it): positive kernels and weights
    coarse = ProductConvolution(rng.random((3, 7, 7)), 0.1 + rng.random((3, 4, 3)),
                                shape=(48, 37), grid=(np.linspace(-3.0, 50.0, 4),
                                                      np.array([0.0, 13.7, 36.0])))
    for op in (
        coarse,
        ProductConvolution(rng.random((2, 5, 5)), 0.1 + rng.random((2, 9, 8)), metadata=meta),
    ):
        path = tmp_path / "model.npz"
        op.save(path)
        op2 = load_operator(path)
        assert op2.image_shape == op.image_shape and op2.is_full_resolution == op.is_full_resolution
        assert np.array_equal(op2.basis, op.basis)
        assert np.array_equal(op2.coefficients, op.coefficients)
        assert op2.metadata == op.metadata
        u = rng.standard_normal(op.image_shape)
        assert np.array_equal(op2.apply(u), op.apply(u))
    assert op2.metadata == {"residual": 0.125, "n_beads": 17, "sizes": [0, 1, 2]}
    with np.load(path, allow_pickle=False) as data:
        header = json.loads(data["header"].tobytes().decode())
    assert header["format"] == FORMAT_NAME and header["version"] == FORMAT_VERSION
    assert header["software"].startswith("napari-psfspace ")
    # no temporary files left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.npz"]


@pytest.mark.parametrize("damage, says", [
    ("negated", "sums to -"), ("zero weights", "sums to 0"), ("zero kernels", "sums to 0"),
    ("shape", "does not match its grid"),
])
def test_a_model_file_that_is_no_blur_is_refused_by_the_loader(tmp_path, rng, damage, says):
    """Every door loads a model through ``load_operator``: a file whose PSF sums to zero
    or less at a node, or whose field is far larger than its grid, is refused there."""
    basis, coef = rng.random((3, 7, 7)), 0.1 + rng.random((3, 4, 3))
    shape, grid = (48, 37), (np.linspace(0, 47, 4), np.linspace(0, 36, 3))
    if damage == "negated":
        coef = -coef
    elif damage == "zero weights":
        coef = 0 * coef
    elif damage == "zero kernels":
        basis = 0 * basis
    elif damage == "shape":
        shape = (200000, 200000)
    ProductConvolution(basis, coef, shape=shape, grid=grid).save(tmp_path / "m.npz")
    with pytest.raises(ValueError, match=says):
        load_operator(tmp_path / "m.npz")


def _rewrite_header(src, dst, **changes):
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    header = json.loads(arrays["header"].tobytes().decode())
    header.update(changes)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez(dst, **arrays)


def test_load_rejects_bad_files(tmp_path, rng):
    op = _coarse_model(rng)
    good = tmp_path / "good.npz"
    op.save(good)

    future = tmp_path / "future.npz"
    _rewrite_header(good, future, version=2)
    msg = r"version 2 is newer than this napari-psfspace supports \(1\)"
    with pytest.raises(ValueError, match=msg):
        load_operator(future)

    wrong = tmp_path / "wrong.npz"
    _rewrite_header(good, wrong, format="something-else")
    with pytest.raises(ValueError, match="not a napari-psfspace model file.*something-else"):
        load_operator(wrong)

    rand = tmp_path / "random.npz"
    np.savez(rand, a=rng.random(5))
    with pytest.raises(ValueError, match="not a napari-psfspace model file.*no 'header'"):
        load_operator(rand)

    text = tmp_path / "notes.txt"
    text.write_text("hello, this is not a model\n")
    with pytest.raises(ValueError, match="not a napari-psfspace model file"):
        load_operator(text)

    npy = tmp_path / "array.npy"
    np.save(npy, np.zeros(3))
    with pytest.raises(ValueError, match="not a napari-psfspace model file"):
        load_operator(npy)

    # a consistent header but arrays that do not fit together
    with np.load(good, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["grid_y"] = arrays["grid_y"][:-1]
    broken = tmp_path / "broken.npz"
    np.savez(broken, **arrays)
    with pytest.raises(ValueError, match="inconsistent model file"):
        load_operator(broken)

    with pytest.raises(FileNotFoundError):
        load_operator(tmp_path / "missing.npz")


def test_failed_save_leaves_existing_file_untouched(tmp_path, rng, monkeypatch):
    op = _coarse_model(rng)
    target = tmp_path / "model.npz"
    target.write_bytes(b"precious previous content")

    def exploding_savez(fh, **arrays):
        fh.write(b"half-written garbage")
        raise RuntimeError("disk full (simulated)")

    monkeypatch.setattr(np, "savez_compressed", exploding_savez)
    with pytest.raises(RuntimeError, match="simulated"):
        op.save(target)
    assert target.read_bytes() == b"precious previous content"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.npz"]


def test_failed_save_into_file_as_directory(tmp_path, rng):
    op = _coarse_model(rng)
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("x")
    with pytest.raises(OSError):
        op.save(not_a_dir / "model.npz")
    assert not_a_dir.read_text() == "x"
    # target is an existing directory: os.replace fails, directory untouched, temp removed
    d = tmp_path / "dir.npz"
    d.mkdir()
    with pytest.raises(OSError):
        op.save(d)
    assert d.is_dir() and list(d.iterdir()) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.npz", "file"]


def test_atomic_write_text_and_permissions(tmp_path):
    target = tmp_path / "a.txt"
    _atomic.atomic_write(target, lambda fh: fh.write("hello"), mode="w", encoding="utf-8")
    assert target.read_text() == "hello"
    os.chmod(target, 0o640)
    _atomic.atomic_write(target, lambda fh: fh.write("again"), mode="w")
    assert target.read_text() == "again"
    assert (target.stat().st_mode & 0o777) == 0o640


def test_saved_file_is_plain_npz_without_pickle(tmp_path, rng):
    op = _coarse_model(rng)
    path = tmp_path / "m.npz"
    op.save(path)
    with zipfile.ZipFile(path) as zf:
        names = sorted(zf.namelist())
    assert names == sorted(
        f"{k}.npy" for k in ("basis", "coefficients", "grid_x", "grid_y", "header", "shape")
    )
    with np.load(path, allow_pickle=False) as data:
        assert all(data[k].dtype != object for k in data.files)


def test_a_killed_write_leaves_nothing_after_the_next(tmp_path):
    """``kill -9`` while the model is being written (the writer sleeps inside the
    temporary file): the destination is untouched, and the next write to the path
    removes the dead writer's temporary file; a missing folder is named, not the
    temporary file."""
    import signal
    import subprocess
    import sys
    import time

    target = tmp_path / "m.npz"
    target.write_bytes(b"old")
    code = ("import time, sys; from napari_psfspace.core.common.atomic import atomic_write; "
            f"atomic_write({str(target)!r}, lambda fh: (fh.write(b'half'), fh.flush(), "
            "print('in', flush=True), time.sleep(60)))")
    for _ in range(3):  # each writer removes the one killed before it
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
        assert proc.stdout.readline().strip() == b"in"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        stale = [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
        assert len(stale) == 1 and target.read_bytes() == b"old"
    # a live writer's file is kept: this process's pid is alive
    live = tmp_path / f".m.npz.{os.getppid()}.abc.tmp"
    live.write_bytes(b"")
    time.sleep(0.01)
    _atomic.atomic_write(target, lambda fh: fh.write(b"new"))
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["m.npz", live.name])
    # a dead writer of another file in the folder: removed by the next write there
    proc = subprocess.Popen([sys.executable, "-c", code.replace("m.npz", "other.tif")],
                            stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"in"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert any(p.name.startswith(".other.tif.") for p in tmp_path.iterdir())
    _atomic.atomic_write(target, lambda fh: fh.write(b"newer"))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["m.npz", live.name])
    with pytest.raises(FileNotFoundError, match="missing"):
        _atomic.atomic_write(tmp_path / "missing" / "x.npz", lambda fh: fh.write(b"x"))
