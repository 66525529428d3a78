"""A slice's PSF radius follows focus: the median of the slice and its neighbours, and
the reason, with the spots behind it, where the slice alone would jump."""

import numpy as np
import pytest
from scipy import ndimage as ndi

import napari_psfspace as ps
from napari_psfspace.core.beads.focus import SLICE_RATIO
from napari_psfspace.core.beads.radius import suggest_psf_radius
from napari_psfspace.core.beads.slice_radius import suggest_slice_radius


@pytest.fixture(scope="module")
def beads():
    return ps.simulate_beads((256, 256), 25, seed=4)


def test_a_slice_that_jumps_gets_the_median_and_its_spots_named(beads):
    """The middle slice blurred by a Gaussian of 4 px sigma reads more than 1.5x its
    neighbours: the radius used is the median of the three readings, and the reason
    names the slice, the jump and spots at beads (the blur keeps them in place)."""
    image, truth = beads
    wide = ndi.gaussian_filter(image.astype(float), 4.0)
    stack = np.stack([image, wide, image]).astype(np.float32)
    found = suggest_slice_radius(stack, 1)
    readings = [found.readings[k] for k in (0, 1, 2)]
    assert readings[1] > SLICE_RATIO * readings[0]  # the case: a jump
    assert found.radius == pytest.approx(float(np.median(readings)))
    assert found.own == pytest.approx(readings[1])
    assert "slice 1 alone reads" in found.reason and "widest" in found.reason
    assert 1 <= len(found.drivers) <= 3
    gaps = np.min(np.hypot(*(found.drivers[:, None, :2] - truth.positions[None]).transpose(
        2, 0, 1)), axis=1)
    assert np.all(gaps <= 3.0), gaps  # each spot named is a bead


def test_a_steady_stack_reads_its_own_radius_without_a_reason(beads):
    image, _ = beads
    rng = np.random.default_rng(0)
    stack = np.stack([image + rng.normal(0, 1, image.shape) for _ in range(3)])
    found = suggest_slice_radius(stack.astype(np.float32), 1)
    assert found.reason == "" and len(found.drivers) == 0
    own = suggest_psf_radius(stack[1])
    assert found.own == pytest.approx(own)
    assert max(found.radius / own, own / found.radius) <= SLICE_RATIO


def test_an_empty_slice_takes_its_neighbours_and_says_so(beads):
    image, _ = beads
    empty = np.random.default_rng(1).normal(100, 1, image.shape)
    stack = np.stack([image, empty, image]).astype(np.float32)
    found = suggest_slice_radius(stack, 1)
    assert np.isnan(found.own) and "shows no spot" in found.reason
    assert found.radius == pytest.approx(found.readings[0])


def test_bad_index_names_the_argument(beads):
    image, _ = beads
    with pytest.raises(ValueError, match="`index`"):
        suggest_slice_radius(np.stack([image, image]), 2)
