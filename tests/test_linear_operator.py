"""The blur operators as scipy LinearOperators: flattened shape, ``@``, ``.H``, matvec
and rmatvec, scipy's ``lsqr``, pylops' ``cgls`` and the docs page's examples.

The references are dense matrices built column by column from ``apply`` on unit
impulses, solved with numpy: a least-squares solution is then checked against linear
algebra that shares no code with the solvers.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import tifffile
from scipy.sparse.linalg import LinearOperator, aslinearoperator, lsqr

from napari_psfspace import ProductConvolution
from napari_psfspace.core.volume.blocks3d import BlockedOperator3D
from napari_psfspace.core.volume.operator3d import ProductConvolution3D

DOCS = Path(__file__).resolve().parents[1] / "docs" / "linear-operator.md"


def _operator(shape=(24, 20)) -> ProductConvolution:
    """Two Gaussian kernels (sd 1 and 1.6 px) under positive maps: well enough
    conditioned for a damped least-squares problem to converge in a few hundred steps."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[-3:4, -3:4]
    basis = np.array([np.exp(-(yy**2 + xx**2) / (2 * s * s)) for s in (1.0, 1.6)])
    basis /= basis.sum(axis=(1, 2), keepdims=True)
    grid = (np.linspace(0, shape[0] - 1, 3), np.linspace(0, shape[1] - 1, 3))
    return ProductConvolution(basis, rng.random((2, 3, 3)) + 0.5, shape=shape, grid=grid)


def _operator_3d() -> ProductConvolution3D:
    rng = np.random.default_rng(1)
    gy, gx = np.linspace(0, 23, 3), np.linspace(0, 19, 3)
    return ProductConvolution3D(rng.random((2, 3, 5, 5)), rng.random((2, 3, 3)),
                                shape=(4, 24, 20), grid=(gy, gx), plane=1)


def _dense(op) -> np.ndarray:
    n = op.shape[1]
    return np.column_stack([op.apply(e.reshape(op.image_shape)).ravel()
                            for e in np.eye(n)])


@pytest.mark.parametrize("make", [_operator, _operator_3d])
def test_the_operator_is_a_linear_operator_on_flattened_images(make):
    op = make()
    n = int(np.prod(op.image_shape))
    assert isinstance(op, LinearOperator) and aslinearoperator(op) is op
    assert op.shape == (n, n) and op.dtype == np.float64
    rng = np.random.default_rng(2)
    u, v = rng.standard_normal((2, *op.image_shape))
    hu, htv = op.apply(u), op.adjoint(v)
    # the same calls underneath: equal to the bit
    assert np.array_equal(op @ u, hu) and np.array_equal(op.H @ v, htv)
    assert np.array_equal(op @ u.ravel(), hu.ravel())
    assert np.array_equal(op.matvec(u.ravel()), hu.ravel())
    assert np.array_equal(op.rmatvec(v.ravel()), htv.ravel())
    assert np.array_equal(op.H.matvec(v.ravel()), htv.ravel())
    assert np.array_equal(op.adjoint() @ v, htv) and op.H.H is op
    # a block of vectors (matmat), column by column
    block = np.stack([u.ravel(), v.ravel()], axis=1)
    assert np.array_equal(op @ block, np.stack([hu.ravel(), op.apply(v).ravel()], axis=1))
    # dot test through scipy's interface: rounding of sums of n terms in float64
    lhs, rhs = np.vdot(op.matvec(u.ravel()), v.ravel()), np.vdot(u.ravel(),
                                                                   op.rmatvec(v.ravel()))
    assert abs(lhs - rhs) <= 1e-12 * np.linalg.norm(hu) * np.linalg.norm(v) * n ** 0.5


def test_a_3d_operator_takes_any_depth_through_matmul():
    op = _operator_3d()
    u = np.random.default_rng(3).standard_normal((7, *op.image_shape[1:]))
    assert np.array_equal(op @ u, op.apply(u)) and np.array_equal(op.H @ u, op.adjoint(u))


def test_the_blocked_operator_is_one_too():
    blocked = BlockedOperator3D(_operator_3d(), block=12)
    u = np.random.default_rng(4).standard_normal(blocked.image_shape).astype(np.float32)
    assert blocked.shape == (u.size, u.size)
    # ``@`` computes in the operator's float64 and ``apply`` keeps float32: the two differ
    # by float32's rounding of FFTs over a few hundred points, about 1e-7 * log2(n) of the
    # largest value; 1e-5 of it leaves room and still catches a wrong block or kernel
    for got, want in ((blocked @ u, blocked.apply(u)), (blocked.H @ u, blocked.adjoint(u))):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * np.abs(want).max())


def test_lsqr_solves_the_damped_problem_of_the_dense_matrix():
    """``lsqr(op, y.ravel())`` runs; damped, its solution equals numpy's solve of the
    normal equations ``(H^T H + d^2 I) u = H^T y``. ``||H|| <= 3`` (two kernels of sum
    1 under maps below 1.5), so their condition number is at most ``(9 + d^2) / d^2`` =
    3601, and two solutions of it agree to about that times float64's 2.2e-16, 1e-12;
    1e-8 leaves room."""
    op = _operator()
    dense = _dense(op)
    u = np.random.default_rng(5).random(op.image_shape)
    y = op @ u
    assert lsqr(op, y.ravel(), iter_lim=5)[0].shape == (u.size,)
    d = 0.05
    ref = np.linalg.solve(dense.T @ dense + d * d * np.eye(u.size), dense.T @ y.ravel())
    got = lsqr(op, y.ravel(), damp=d, atol=1e-14, btol=1e-14, iter_lim=5000)[0]
    assert np.linalg.norm(got - ref) <= 1e-8 * np.linalg.norm(ref)


def test_pylops_cgls_matches_the_dense_solution():
    """pylops' CGLS on ``to_pylops()`` (it adds ``damp^2 ||u||^2``, as lsqr does)
    against the same dense solve. CG on a system of condition number 3601 gains a factor
    (sqrt(3601) - 1) / (sqrt(3601) + 1) = 0.967 an iteration: after 1000, 3e-15, below
    the rounding (about 1e-12) that the 1e-5 bound leaves room for."""
    pylops = pytest.importorskip("pylops", reason="pylops is not installed")
    op = _operator()
    dense = _dense(op)
    u = np.random.default_rng(6).random(op.image_shape)
    y = op @ u
    d = 0.05
    ref = np.linalg.solve(dense.T @ dense + d * d * np.eye(u.size), dense.T @ y.ravel())
    pop = op.to_pylops()
    assert pop.dims == op.image_shape and pop.dimsd == op.image_shape
    got = pylops.optimization.basic.cgls(pop, y, niter=1000, damp=d, tol=0.0)[0]
    assert got.shape == op.image_shape
    assert np.linalg.norm(got.ravel() - ref) <= 1e-5 * np.linalg.norm(ref)


def test_the_docs_examples_run(tmp_path, monkeypatch):
    """The two examples of docs/linear-operator.md, as written, on a saved model and a
    blurred image: lsqr's result has the image's shape, pyproximal's is non-negative and
    fits the data better than zero does."""
    pytest.importorskip("pyproximal", reason="pyproximal is not installed")
    blocks = re.findall(r"```python\n(.*?)```", DOCS.read_text(), re.S)
    assert len(blocks) == 2, "the page holds two examples"
    op = _operator()
    op.save(tmp_path / "model.npz")
    truth = np.zeros(op.image_shape)
    truth[5, 7], truth[15, 12] = 100.0, 60.0
    tifffile.imwrite(tmp_path / "sample.tif", (op @ truth).astype(np.float32))
    monkeypatch.chdir(tmp_path)
    space: dict = {}
    exec(compile(blocks[0], "lsqr example", "exec"), space)
    assert space["u"].shape == op.image_shape
    exec(compile(blocks[1], "pyproximal example", "exec"), space)
    u, y = space["u"], space["y"]
    assert u.shape == op.image_shape and u.min() >= 0
    assert np.linalg.norm(op @ u - y) < 0.1 * np.linalg.norm(y)
