"""Outliers judged by one held-out error per bead (core/model/outliers.judge_outliers): the rim
of a steep field kept, gross misfits left out, the surround rule on known layouts."""

import numpy as np

from napari_psfspace.core.model.outliers import surrounded
from napari_psfspace.core.model.pca import learn_basis


def _gaussians(pos, shape, size=21, sigma_of=None):
    """Sum-1 elliptical Gaussians whose widths vary smoothly (and steeply) over the field."""
    g = np.arange(size) - size // 2
    out = []
    for y, x in pos:
        u, v = x / shape[1] - 0.5, y / shape[0] - 0.5
        sy, sx = 1.6 + 2.0 * u**2 + 1.2 * v, 1.6 + 1.5 * v**2 - 0.8 * u
        p = np.exp(-0.5 * (g[:, None] ** 2 / sy**2 + g[None, :] ** 2 / sx**2))
        out.append(p / p.sum())
    return np.array(out)


def test_surround_rule_on_a_grid():
    yy, xx = np.meshgrid(np.arange(7.0), np.arange(7.0), indexing="ij")
    pos = np.stack([yy.ravel(), xx.ravel()], 1) * 10 + np.random.default_rng(0).normal(
        0, 0.5, (49, 2))
    inner = surrounded(pos).reshape(7, 7)
    assert inner[2:-2, 2:-2].all()  # two rings in: every direction has neighbours
    assert not inner[0].any() and not inner[-1].any()  # the outer ring: half a turn empty
    assert not inner[:, 0].any() and not inner[:, -1].any()


def test_a_noise_free_steep_field_keeps_every_bead_and_a_doublet_is_left_out():
    rng = np.random.default_rng(1)
    shape = (1000, 1000)
    pos = rng.uniform(20, 980, (120, 2))
    psfs = _gaussians(pos, shape)
    basis = learn_basis(psfs, 6, positions=pos)
    assert basis.inliers.all(), np.flatnonzero(~basis.inliers)
    bad = psfs.copy()
    k = int(np.argmin(np.hypot(*(pos - 500).T)))  # the bead nearest the centre
    bad[k] = 0.5 * bad[k] + 0.5 * np.roll(bad[k], 4, axis=1)  # a doublet 4 px apart
    corner = int(np.argmin(np.hypot(*(pos - 0).T)))  # and one in a corner
    bad[corner] = 0.5 * bad[corner] + 0.5 * np.roll(bad[corner], 5, axis=0)
    basis = learn_basis(bad, 6, positions=pos)
    assert not basis.inliers[k] and not basis.inliers[corner]
    assert basis.inliers.sum() == len(pos) - 2


def test_z_threshold_is_checked_before_any_work():
    from napari_psfspace.core.model.estimate import iter_estimate

    for bad in ("x", -1.0, float("nan"), 0):
        try:
            next(iter_estimate(np.zeros((64, 64)), psf_radius=4, z_threshold=bad))
        except ValueError as err:
            assert "`z_threshold`" in str(err) and repr(bad) in str(err)
        else:
            raise AssertionError(f"z_threshold={bad!r} accepted")


def test_an_infinite_threshold_keeps_every_bead_unjudged():
    rng = np.random.default_rng(2)
    pos = rng.uniform(20, 980, (40, 2))
    basis = learn_basis(_gaussians(pos, (1000, 1000)), 3, positions=pos,
                        z_threshold=np.inf)
    assert basis.inliers.all() and np.isnan(basis.zscores).all()
