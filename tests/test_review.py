"""Patch review numbers: views, outliers, neighbours, saturation."""

import numpy as np
import pytest

from napari_psfspace.core.beads.detect import Beads, detect_beads
from napari_psfspace.core.model.review import VIEWS, iter_patch_review, patch_review
from napari_psfspace.core.simulation import simulate_beads


@pytest.fixture(scope="module")
def scene():
    image, truth = simulate_beads((384, 384), 25, seed=3)
    return image, truth, detect_beads(image, truth.psf_radius)


def test_views_and_index(scene):
    image, truth, beads = scene
    rv = patch_review(image, beads, truth.psf_radius)
    assert set(rv.views) == set(VIEWS)
    k = len(rv)
    assert k == np.count_nonzero(beads.status != "border")
    p = rv.views["raw"].shape[-1]
    for v in rv.views.values():
        assert v.shape == (k, p, p)
    assert np.all(beads.status[rv.index] != "border")
    windowed = rv.views["windowed"]
    assert np.allclose(windowed[:, 0, :], 0) and np.allclose(windowed[:, :, 0], 0)
    assert np.isfinite(rv.zscore[beads.status[rv.index] == "kept"]).all()


def test_planted_doublet_is_flagged(scene):
    image, truth, beads = scene
    img = image.astype(np.float64)
    k = int(np.flatnonzero(beads.kept)[3])
    y, x = np.round(beads.positions[k]).astype(int)
    img[y - 6:y + 7, x + 4:x + 17] += img[y - 6:y + 7, x - 6:x + 7] * 1.5  # a second bead
    rv = patch_review(img, beads, truth.psf_radius)
    row = int(np.flatnonzero(rv.index == k)[0])
    assert rv.outlier[row], rv.zscore[row]
    assert any("outlier" in f for f in rv.flags(row))


def test_neighbour_and_saturated_flags(scene):
    image, truth, beads = scene
    r = truth.psf_radius
    pos = np.array([[100.0, 100.0], [100.0, 100.0 + r], [250.0, 250.0]])
    img = np.full((384, 384), 100, np.uint16)
    img[248:253, 248:253] = np.iinfo(np.uint16).max
    rv = patch_review(img, Beads(pos, np.ones(3)), r)
    assert rv.neighbour.tolist() == [True, True, False]
    assert rv.saturated.tolist() == [False, False, True]
    assert "saturated" in rv.flags(2)


def test_progress_and_error():
    image = np.zeros((64, 64))
    beads = Beads(np.array([[2.0, 2.0]]), np.ones(1))
    with pytest.raises(ValueError, match="border"):
        patch_review(image + 1, beads, 5.0)
    img, truth = simulate_beads((256, 256), 10, seed=1)
    gen = iter_patch_review(img, detect_beads(img, truth.psf_radius), truth.psf_radius)
    fractions = []
    while True:
        try:
            fractions.append(next(gen).fraction)
        except StopIteration:
            break
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
