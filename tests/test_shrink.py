"""The family as the prior of each image's fields (core/family/shrink.py)."""

import numpy as np
import pytest

from napari_psfspace.core.family.estimate import grid_nodes
from napari_psfspace.core.family.shrink import shrunk_fields
from napari_psfspace.core.model.tps import ThinPlateSpline
from napari_psfspace.core.model.voronoi import voronoi_areas

SHAPE = (512, 512)


def _truth(k, pts):
    """Two columns: a field the images share, plus each image's own affine departure
    (an offset and a tilt, as a focus shift and a slide tilt give)."""
    y, x = pts[:, 0] / SHAPE[0] - 0.5, pts[:, 1] / SHAPE[1] - 0.5
    shared = np.column_stack([0.3 * y ** 2 + 0.2 * x * y, 0.1 * np.cos(3 * x)])
    rng = np.random.default_rng([7, k])
    off, tilt = rng.normal(0, 0.02, 2), rng.normal(0, 0.02, 2)
    return shared + off + np.outer(y, tilt)


def _stack(noise, n_beads=30, k=10, seed=0):
    rng = np.random.default_rng(seed)
    centers, values = [], []
    for i in range(k):
        pts = rng.uniform(20, 492, size=(n_beads, 2))
        centers.append(pts)
        values.append(_truth(i, pts) + rng.normal(0, noise, (n_beads, 2)))
    return centers, values


def _errors(centers, values):
    """rms error at the nodes of the shrunk fields and of each image's own spline."""
    (gy, gx), nodes = grid_nodes(SHAPE, 32.0)
    fields = shrunk_fields(centers, values, (gy, gx), SHAPE)
    shrunk, own = [], []
    for k, (c, v) in enumerate(zip(centers, values, strict=True)):
        truth = _truth(k, nodes)
        spline = ThinPlateSpline(c, v, weights=voronoi_areas(c, SHAPE),
                                 scale=0.5 * float(np.hypot(*SHAPE)))
        own.append(np.sqrt(np.mean((np.asarray(spline(nodes)) - truth) ** 2)))
        shrunk.append(np.sqrt(np.mean((fields.nodes[k] - truth) ** 2)))
    return np.array(shrunk), np.array(own), fields


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_faint_beads_lean_on_the_family(seed):
    # noise 0.1 per bead against departures of about 0.02: each image's own field
    # follows its noise; the shrunk fields lean on the family's mean (shrink factors
    # 0-0.7 on these seeds) and lose a third of the own fields' error
    shrunk, own, fields = _errors(*_stack(0.1, seed=seed))
    assert fields.shrink.max() < 0.8 and fields.shrink.min() < 0.5
    assert np.all(fields.share() < 0.8)  # (the shrink factors weighted by tau^2)
    assert shrunk.mean() < 0.8 * own.mean()
    assert np.all(shrunk < 1.1 * own)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bright_beads_keep_their_own_departure(seed):
    # noise 0.001: each image's departure is measured, and the prior keeps it whole
    # (shrink >= 0.99 on these seeds); the residual about the family's mean field is
    # smoother than the field itself, so the spline of it is no worse than the own
    shrunk, own, fields = _errors(*_stack(0.001, seed=seed))
    assert fields.shrink.min() > 0.95
    assert np.all(fields.share() > 0.95)
    assert np.all(shrunk <= 1.05 * own)
    assert shrunk.max() < 0.01  # ten times the beads' noise


def test_images_with_few_or_no_beads_get_the_family_mean_plus_their_offset():
    centers, values = _stack(0.01)
    centers[3], values[3] = centers[3][:2], values[3][:2]  # 2 beads: a constant departure
    centers[4], values[4] = centers[4][:0], values[4][:0]  # none: the family's mean
    (gy, gx), nodes = grid_nodes(SHAPE, 32.0)
    fields = shrunk_fields(centers, values, (gy, gx), SHAPE)
    mean = np.mean([fields.nodes[k] for k in (0, 1, 2, 5, 6)], axis=0)
    assert fields.shrink[4].max() == 0.0
    assert np.all(np.isfinite(fields.nodes[3])) and np.all(np.isfinite(fields.nodes[4]))
    assert len(fields.beads[4]) == 0 and fields.beads[3].shape == (2, 2)
    # the field of the image without beads is the family's mean (up to the departures
    # of the others, which average out over 9 images)
    assert np.abs(fields.nodes[4] - mean).max() < 0.05


@pytest.mark.parametrize("noise", [0.02, 0.05])
def test_the_shrunk_fields_at_the_beads_are_those_at_the_nodes(noise):
    centers, values = _stack(noise, k=4)
    (gy, gx), _ = grid_nodes(SHAPE, 32.0)
    fields = shrunk_fields(centers, values, (gy, gx), SHAPE)
    # the bead values are the mean field interpolated bilinearly plus the departure's
    # spline at the bead: against the nodes' field interpolated the same way, the
    # difference is the bilinear interpolation of the departure (small on 32 px cells)
    from napari_psfspace.core.family.result import space_at
    for k in range(4):
        grid_field = fields.nodes[k].T.reshape(2, len(gy), len(gx))
        at = space_at(grid_field, (gy, gx), centers[k])
        assert np.abs(at - fields.beads[k]).max() < 5e-3


def test_a_fixed_factor_gives_the_mean_at_zero_and_the_whole_departure_at_one():
    centers, values = _stack(0.05, k=5)
    (gy, gx), _ = grid_nodes(SHAPE, 32.0)
    eb = shrunk_fields(centers, values, (gy, gx), SHAPE)
    zero = shrunk_fields(centers, values, (gy, gx), SHAPE, factor=0.0)
    one = shrunk_fields(centers, values, (gy, gx), SHAPE, factor=1.0)
    half = shrunk_fields(centers, values, (gy, gx), SHAPE, factor=0.5)
    # factor 0: every image's field is the family's mean, the same for all
    for k in range(1, 5):
        np.testing.assert_array_equal(zero.nodes[k], zero.nodes[0])
    assert np.all(zero.shrink == 0.0) and np.all(one.shrink == 1.0)
    # the fields are linear in the factor: mean + factor x departure
    for k in range(5):
        np.testing.assert_allclose(half.nodes[k], 0.5 * (zero.nodes[k] + one.nodes[k]),
                                   rtol=0, atol=1e-12)
        np.testing.assert_allclose(half.beads[k], 0.5 * (zero.beads[k] + one.beads[k]),
                                   rtol=0, atol=1e-12)
    # the empirical Bayes fields lie between the two, column by column
    for k in range(5):
        s = eb.shrink[k]
        np.testing.assert_allclose(eb.nodes[k], zero.nodes[k] + s * (one.nodes[k]
                                                                      - zero.nodes[k]),
                                   rtol=0, atol=1e-12)
    np.testing.assert_array_equal(one.tau2, eb.tau2)


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_a_factor_outside_zero_one_is_refused(bad):
    centers, values = _stack(0.05, k=3)
    (gy, gx), _ = grid_nodes(SHAPE, 32.0)
    with pytest.raises(ValueError, match="`factor` must be None or a number in"):
        shrunk_fields(centers, values, (gy, gx), SHAPE, factor=bad)


def test_bead_weights_cap_only_the_outlying_beads():
    from napari_psfspace.core.family.shrink import MIN_BEADS_ROBUST, bead_weights

    rng = np.random.default_rng(3)
    res = rng.normal(0, 0.01, (30, 8))
    # Gaussian residuals on 8 columns pass 2 robust sd with probability about 1e-4
    assert np.all(bead_weights(res) == 1.0)
    res[5] *= 10.0  # one bead ten times as noisy: its rms is about 10 robust sd
    w = bead_weights(res)
    assert np.all(w[np.arange(30) != 5] == 1.0)
    assert 0.01 < w[5] < 0.1  # (2 / ~10)^2
    # its weighted squared rms is that of a bead at the scale
    mad = 1.4826 * np.median(np.abs(res - np.median(res, axis=0)), axis=0)
    u = np.sqrt(np.mean((res[5] / mad) ** 2))
    assert w[5] * u ** 2 == pytest.approx(4.0, rel=1e-12)
    # a column without spread is left out, not divided by zero
    res[:, 0] = 0.0
    assert np.all(np.isfinite(bead_weights(res)))
    # too few beads to measure a spread by: all kept
    assert np.all(bead_weights(res[:MIN_BEADS_ROBUST - 1] * 100) == 1.0)


@pytest.mark.parametrize("seed", [5, 6])
def test_an_outlying_bead_does_not_carry_its_image_s_field(monkeypatch, seed):
    from napari_psfspace.core.family import shrink

    centers, values = _stack(0.02, k=6, seed=seed)
    bad = values[0].copy()
    bad[7] += 0.5  # 25 times the beads' noise on both columns (a bead mis-normalised)
    (gy, gx), nodes = grid_nodes(SHAPE, 32.0)
    truth = _truth(0, nodes)
    near = np.hypot(*(nodes - centers[0][7]).T) < 100  # the nodes it can pull

    def error(vals):
        f = shrunk_fields(centers, [vals] + values[1:], (gy, gx), SHAPE)
        e2 = (f.nodes[0] - truth) ** 2
        return np.sqrt(e2.mean()), np.sqrt(e2[near].mean()), f

    clean, _, _ = error(values[0])
    robust, robust_near, fields = error(bad)
    # its standardized residual stays beyond 9 robust sd once its weight is cut
    assert fields.weights[0][7] < 0.05
    # the others keep theirs (Gaussian noise on 2 columns passes 2 robust sd with
    # probability exp(-4), 2 %: one bead or two of 30 is cut a little)
    assert np.delete(fields.weights[0], 7).mean() > 0.95
    # what is left of it (a weight worth 2 robust sd) costs at most half the clean error
    # (seed 5: the bead sits where few others do; 1.4x there)
    assert robust < 1.6 * clean
    # the same fields without the robust weights follow the outlier
    monkeypatch.setattr(shrink, "ROBUST_SCALE", np.inf)
    plain, plain_near, fields = error(bad)
    assert np.all(fields.weights[0] == 1.0)
    assert plain > 1.5 * robust and plain_near > 3 * robust_near
