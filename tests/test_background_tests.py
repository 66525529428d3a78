"""The residual tests on the bead-free background (core/analysis.py): line patterns and
window structure, measured against the noise and the noise model's own uncertainty."""

import numpy as np

from napari_psfspace.core.beads.noise import NoiseModel
from napari_psfspace.core.diagnosis.background_tests import line_pattern, window_structure
from napari_psfspace.core.diagnosis.statistics import FALLBACK_SCALE_ERROR, noise_scale_error


def _flat(seed, shape=(512, 512), level=20.3, sd=0.3, quantise=True):
    rng = np.random.default_rng(seed)
    img = level + 0.002 * np.arange(shape[1])[None, :] + rng.normal(0, sd, shape)
    return np.round(img) if quantise else img


def test_line_pattern_on_an_integer_image_with_noise_below_one_adu():
    # an 8-bit low-gain export: the noise is 0.3 ADU and the level crosses half-integers.
    # The lines' medians flip between two integers (the former statistic read z 20-75 on
    # such still scenes of the family, chi2/dof 11.7 here); their clipped means do not
    noise = NoiseModel(0.0, 0.3**2 + 1 / 12, kind="camera", min_variance=1 / 12)
    free = np.ones((512, 512), bool)
    for seed in range(3):
        img = _flat(seed)
        level = np.full(img.shape, img.mean()) + 0.002 * np.arange(512)[None, :]
        for axis in (0, 1):
            z = line_pattern(img - level, level, free, noise, axis)["z"]
            assert abs(z) < 4, (seed, axis, z)  # measured |z| <= 1.8
    # column offsets of 0.2 ADU sd (below the pixel noise) do stand out
    rng = np.random.default_rng(7)
    img = np.round(_flat(0, quantise=False) + rng.normal(0, 0.2, 512)[None, :])
    level = np.full(img.shape, img.mean()) + 0.002 * np.arange(512)[None, :]
    assert line_pattern(img - level, level, free, noise, 0)["z"] > 20
    assert abs(line_pattern(img - level, level, free, noise, 1)["z"]) < 4
    # a field that is not square (the starfield is 3072 x 2048): one line per column
    wide = np.round(_flat(1, shape=(300, 700)))
    lev = np.full(wide.shape, wide.mean()) + 0.002 * np.arange(700)[None, :]
    cols = line_pattern(wide - lev, lev, np.ones(wide.shape, bool), noise, 0)
    rows = line_pattern(wide - lev, lev, np.ones(wide.shape, bool), noise, 1)
    assert cols["n_lines"] == 700 and rows["n_lines"] == 300
    assert abs(cols["z"]) < 4 and abs(rows["z"]) < 4


def test_structure_excess_is_weighed_against_the_noise_models_own_error():
    rng = np.random.default_rng(3)
    shape = (480, 480)
    free = np.ones(shape, bool)
    level = np.full(shape, 100.0)
    truth = NoiseModel(1.0, 0.0, kind="camera")
    img = rng.normal(0.0, 10.0, shape)
    # a model whose gain is 5 % low: on 400 windows the sampling error alone makes the
    # 5 % excess variance a z of 17; with the model's stated 5 % error, about 1
    low = NoiseModel(0.95, 0.0, kind="photon transfer", checks={"gain_relative_error": 0.05})
    blind = window_structure(img, level, free, low, 24)["z"]
    weighed = window_structure(img, level, free, low, 24,
                                scale_error=noise_scale_error(low))["z"]
    assert blind > 10 and abs(weighed) < 2.5
    assert abs(window_structure(img, level, free, truth, 24)["z"]) < 3
    # blobs of the patch's scale (10 noise sd, one per 1150 px^2) stand out of both
    # (measured z 16.5). The price: the excess must pass the model's own error, so 60
    # blobs of 4 sd, chi2/dof 1.08, now read z 1.7
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    blobs = sum(100 * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 6.0**2))
                for cy, cx in rng.uniform(0, 480, size=(200, 2)))
    z = window_structure(img + blobs, level, free, low, 24,
                          scale_error=noise_scale_error(low))["z"]
    assert z > 8


def test_scale_error_by_kind_of_noise_model():
    assert noise_scale_error(NoiseModel(1.0, 0.0, kind="camera")) == 0.0
    pt = NoiseModel(1.0, 0.0, kind="photon transfer", checks={"gain_relative_error": 0.07})
    assert noise_scale_error(pt) == 0.07
    assert noise_scale_error(NoiseModel(0.0, 4.0, kind="constant")) == FALLBACK_SCALE_ERROR
