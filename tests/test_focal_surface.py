"""Beads registered in z before the 3D PCA (``core/volume/focal_surface``): each bead's
focus from its axial profile, the field's focal surface through the foci, beads far off
it left out, and each patch moved onto the surface.

The stack: a tilted and curved slide (NA 1.4, 100 nm pixels and planes, +-1.2 µm) with
beads scattered +-0.5 µm about it, and one bead floating 1.6 µm above it (its focus is
not inside the stack). The rules for a bead off the surface are checked on planted foci.
"""

import numpy as np
import pytest

from napari_psfspace.core.beads.detect import OFF_FOCUS, OUTLIER
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.simulation.focus import simulate_focus_series
from napari_psfspace.core.simulation.optics import Optics
from napari_psfspace.core.volume import iter_estimate_operator_3d
from napari_psfspace.core.volume.focal_surface import (
    axial_centres,
    design,
    fit_focal_surface,
    shift_planes,
)
from napari_psfspace.core.volume.measures import model_measures, psf_measures
from napari_psfspace.core.volume.patches3d import extract_patches_3d

SIGMA = 2.5  # planes: the test profiles' Gaussian


def _gauss(z, c):
    return np.exp(-(z - c) ** 2 / (2 * SIGMA ** 2))


def test_the_axial_centre_is_the_profiles_peak_and_its_width_the_half_maximum_width():
    """The logarithm of a Gaussian is a parabola: the vertex through three planes is
    exact. The ``[1, 2, 1] / 4`` smoothing multiplies the profile's spectrum by
    ``cos^2(w / 2)``, which departs from a Gaussian's by ``w^4 / 96``, a quarter per mille
    at the profile's frequencies (``w ~ 1 / sd``): 1e-3 planes bounds the vertex's move.
    The width is ``2.355 sd`` within 0.2 planes: the sampled peak lies up to
    ``h^2 / (8 sd^2)`` = 2 % below the true one (0.04 planes a side), and linear
    interpolation of the crossings adds at most ``max|f''| / (8 min|f'|)`` = 0.049 a side.
    A profile skewed by a tail (spherical aberration) keeps its focus near its peak."""
    z = np.arange(40.0)
    centres = np.array([13.3, 20.0, 20.5, 26.77])
    got, width = axial_centres(np.stack([3.0 * _gauss(z, c) for c in centres]))
    assert np.abs(got - centres).max() <= 1e-3
    assert np.abs(width - 2 * np.sqrt(2 * np.log(2)) * SIGMA).max() <= 0.2
    # a peak at 15 with a tail three times as wide beyond it: the half-maximum crossings
    # lie 2.94 planes before and 8.83 after it (their midpoint 2.94 planes away); the
    # focus stays within the plane of the peak (the smoothing leans it toward the tail)
    tail = np.where(z < 15, _gauss(z, 15), np.exp(-(z - 15) ** 2 / (2 * (3 * SIGMA) ** 2)))
    focus, w = axial_centres(tail[None])
    assert abs(focus[0] - 15) <= 1.0 and w[0] == pytest.approx(2.94 + 8.83, abs=0.2)
    # a half maximum beyond the stack, or no light: no focus
    edge, _ = axial_centres(np.stack([_gauss(z, 1.0), np.zeros(40), -_gauss(z, 20)]))
    assert np.isnan(edge).all()


def test_a_patch_moves_by_whole_planes_exactly_and_by_part_of_one_to_the_splines_error():
    """A cubic B-spline interpolates within ``5 h^4 max|f''''| / 384`` = 0.001 of a
    Gaussian of sd 2.5 planes and peak 1 (``max|f''''| = 3 / sd^4``)."""
    z = np.arange(40.0)
    psf = np.stack([_gauss(z, 20.0)[:, None, None] * np.ones((1, 2, 2))] * 3)
    out = shift_planes(psf, np.array([0.0, 2.0, 0.37]))
    assert np.array_equal(out[0], psf[0])
    assert np.abs(out[1, :, 0, 0] - _gauss(z, 18.0)).max() <= 1e-12
    assert np.abs(out[2, :, 0, 0] - _gauss(z, 20.0 - 0.37)).max() <= 0.001


def test_the_surface_through_foci_is_recovered_and_a_far_bead_is_left_out():
    rng = np.random.default_rng(3)
    shape = (600, 800)
    pos = rng.uniform(0, 1, (50, 2)) * shape
    terms = ("constant", "tilt_row", "tilt_col", "curvature")
    truth = np.array([30.0, 2.0, -1.5, 3.0])
    sd = 0.3
    foci = design(pos, shape, terms) @ truth + rng.normal(0, sd, len(pos))
    foci[7] += 9.0  # a bead far off (its width is 6 planes)
    # a stack of 38 planes: the surface is at plane 30 in the centre, 33 in the corners; a
    # bead is off 6 planes (its width) from it, so a focus beyond the stack is
    foci[11], pos[11] = np.nan, (299.5, 399.5)  # unexplained in the centre (30 < 31)
    foci[12], pos[12] = np.nan, (0.0, 0.0)  # and where the surface nears the end (33)
    s = fit_focal_surface(pos, foci, np.full(len(pos), 6.0), shape, depth=38)
    assert s.terms == terms
    assert np.flatnonzero(s.off).tolist() == [7, 11]
    # least squares of 47 beads, 4 terms: the surface's rms error is sd sqrt(4 / 47) at
    # the beads; 3 times that bounds it with room for the draw
    grid = np.stack(np.meshgrid(np.linspace(0, 599, 9), np.linspace(0, 799, 9),
                                indexing="ij"), -1).reshape(-1, 2)
    err = s(grid) - design(grid, shape, terms) @ truth
    assert np.sqrt(np.mean(err ** 2)) <= 3 * sd * np.sqrt(4 / 47)
    # fewer beads, fewer terms: a tilt from 5, a constant below
    assert fit_focal_surface(pos[:6], foci[:6], np.full(6, 6.0), shape).terms == terms[:3]
    assert fit_focal_surface(pos[:3], foci[:3], np.full(3, 6.0), shape).terms == terms[:1]
    # no focus at all (a stack too short for any profile): a summary JSON can hold
    import json

    none = fit_focal_surface(pos[:4], np.full(4, np.nan), np.full(4, np.nan), shape)
    assert not none.off.any() and np.isnan(none.offsets).all()
    json.dumps(none.summary(0.1), allow_nan=False)


SHAPE = (512, 512)
DZ = 0.1  # µm


def _slide(pos):
    """The slide's height above the bead plane, µm: a tilt and a curvature."""
    s = design(pos, SHAPE, ("constant", "tilt_row", "tilt_col", "curvature"))
    return s @ np.array([-0.15, 0.25, -0.15, 0.3])


@pytest.fixture(scope="module")
def slide():
    """Beads scattered +-0.5 µm about the slide, the first one 1.6 µm above it."""
    def heights(pos, rng):
        h = _slide(pos) + rng.uniform(-0.5, 0.5, len(pos))
        h[0] = _slide(pos[:1])[0] + 1.6
        return h

    z = np.round(np.arange(-1.2, 1.2 + DZ / 2, DZ), 6)
    stack, series = simulate_focus_series(SHAPE, 36, z, optics=Optics(1.4, 0.6, 0.1),
                                          aberrations=None, seed=1, bead_z=heights,
                                          min_separation=45)
    est = run_with_progress(iter_estimate_operator_3d(stack, psf_radius=10,
                                                      voxel_size=(DZ, 0.1, 0.1)))
    return stack, series, est


def test_the_focal_surface_of_a_tilted_curved_slide_is_found_and_a_far_bead_left_out(slide):
    stack, series, est = slide
    s = est.surface
    plane0 = float(np.interp(0.0, series.z_um, np.arange(len(series.z_um))))
    grid = np.stack(np.meshgrid(np.linspace(0, 511, 9), np.linspace(0, 511, 9),
                                indexing="ij"), -1).reshape(-1, 2)
    err_um = (s(grid) - plane0) * DZ - _slide(grid)
    # beads uniform over +-0.5 µm (sd 0.29 µm), about 35 of them, 4 terms: the surface's
    # rms error is near 0.29 sqrt(4 / 35) = 0.098 µm; 1.5 times that bounds the draw
    assert np.sqrt(np.mean(err_um ** 2)) <= 1.5 * 0.098
    # the floating bead has no focus inside the stack; with beads scattered +-0.5 µm the
    # surface's limit (four robust sd, 1.5 µm) reaches past the stack's ends, so the
    # focus rule cannot judge it: it is still not in the model (the PCA's outlier test)
    far = np.argmin(np.hypot(*(est.beads.positions - series.positions[0]).T))
    assert est.beads.status[far] in (OFF_FOCUS, OUTLIER)
    meta = est.operator.metadata
    assert abs(meta["focal_surface"]["tilt_um"] - 2 * np.hypot(0.25, 0.15)) <= 0.15
    # each bead's own focus (the slice where z equals its height)
    near = np.array([np.argmin(np.hypot(*(series.positions - c).T))
                     for c in est.patches.centers])
    focus_um = (est.bead_focus - plane0) * DZ
    assert np.sqrt(np.nanmean((focus_um - series.bead_z_um[near]) ** 2)) <= 0.02


def test_registered_beads_give_the_true_axial_width_and_unregistered_ones_do_not(slide):
    """The model at the field's centre against the true PSF there (the same measure on
    both): within 5 %. The beads' mean without registration is wider by more than that,
    so the check can fail."""
    stack, series, est = slide
    c = (np.array(SHAPE) - 1) / 2
    size = est.operator.kernel_shape[1]
    z0 = series.focus_index
    true = psf_measures(series.psf_at(*c, size))["fwhm_axial"]
    model = model_measures(est.operator, c[None])["fwhm_axial"][0]
    assert abs(model / true - 1) <= 0.05, (model, true)
    raw = extract_patches_3d(stack.astype(np.float32), est.patches.centers,
                             est.patches.r, plane=z0, z_radius=est.operator.plane)
    wide = psf_measures(raw.psf[raw.flux > 0].mean(axis=0))["fwhm_axial"]
    assert wide / true - 1 > 0.05, (wide, true)
