"""The core-vs-brightness statistic: a nonlinear response, not a PSF model's shape error."""

import numpy as np

from napari_psfspace.core.beads.window import radial_distance
from napari_psfspace.core.diagnosis.bead_tests import core_residuals, core_trend, local_contrast
from napari_psfspace.core.diagnosis.residuals import BeadResiduals


def _gauss(p, sigma):
    r = radial_distance(p)
    g = np.exp(-0.5 * (r / sigma) ** 2)
    return g / g.max()


def _residuals(c=0.0, seed=0, k=200, p=15):
    """Beads of a Gaussian PSF (sigma 1.8 px, widening over the field), modelled with a
    sharper one (sigma 1.6 px: a shape error), Poisson noise, brightness spread 0.5,
    and optionally a compressive response ``y (1 - c y / y_max)``."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 1000, (k, 2))
    amp = 2000.0 * np.exp(0.5 * rng.standard_normal(k))
    bg = np.full(k, 10.0)
    sig = 1.8 + 0.3 * pos[:, 1] / 1000  # the field: wider to the right
    truth = np.stack([a * _gauss(p, s) for a, s in zip(amp, sig, strict=True)]) + bg[:, None, None]
    if c:
        truth = truth * (1 - c * truth / truth.max())
    data = rng.poisson(truth).astype(float)
    model = amp[:, None, None] * _gauss(p, 1.6)[None] + bg[:, None, None]
    ones = np.ones(k)
    return BeadResiduals(pos, amp, bg, data, model, np.maximum(model, 1.0),
                         np.ones_like(data, bool), ones, ones, ones, ones)


def test_a_shape_error_alone_shows_no_trend_and_compression_does():
    core = radial_distance(15) <= 1.5
    zs = []
    for seed in range(5):
        res = _residuals(seed=seed)
        zs.append(core_trend(*core_residuals(res, core), res.positions)[1])
        # the noise-normalised core residual grows with brightness for a shape error
        # alone (the statistic this replaced)
        nres = ((res.data - res.model) / np.sqrt(res.variance))[:, core].mean(axis=1)
        rho = np.corrcoef(np.argsort(np.argsort(res.amplitude)),
                          np.argsort(np.argsort(nres)))[0, 1]
        assert abs(rho) > 0.5
    assert max(abs(z) for z in zs) < 3.0  # threshold 4
    res = _residuals(c=0.15)
    z = core_trend(*core_residuals(res, core), res.positions)[1]
    assert abs(z) > 6.0


def test_local_contrast_removes_a_smooth_field():
    rng = np.random.default_rng(1)
    pos = rng.uniform(0, 100, (300, 2))
    own = rng.standard_normal(300)
    lc = local_contrast(3.0 * pos[:, 0] / 100 + own, pos)
    assert np.corrcoef(lc, pos[:, 0])[0, 1] ** 2 < 0.01
    assert np.corrcoef(lc, own)[0, 1] > 0.85
    v = own.copy()
    v[:5] = np.nan
    assert np.isnan(local_contrast(v, pos)[:5]).all()
    assert np.isfinite(local_contrast(v, pos)[5:]).all()
