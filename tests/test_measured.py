"""The estimator on measured data: the in-focus slice of a Leica SP8 confocal bead stack.

Data: ../shared/data/sp8_confocal_beads (GitHub gerasimenkoab/simple_psf_extractor,
GPL-3.0); HC PL APO 100x/1.40 oil, pixel 44.35 nm, z step 100 nm.
"""

import numpy as np
import pytest
import tifffile

from diagnosis_checks import assert_figures_chain
from napari_psfspace.core.beads.detect import detect_beads
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.io import best_focus_index, read_image


def _fwhm(profile: np.ndarray) -> float:
    half = profile.max() / 2
    above = np.flatnonzero(profile >= half)
    i0, i1 = above[0], above[-1]
    left = i0 - 1 + (half - profile[i0 - 1]) / (profile[i0] - profile[i0 - 1])
    right = i1 + (profile[i1] - half) / (profile[i1] - profile[i1 + 1])
    return float(right - left)


@pytest.fixture(scope="module")
def sp8(shared_data):
    import tifffile

    path = shared_data / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif"
    z = best_focus_index(tifffile.imread(path))
    image, info = read_image(path, index=z)
    return z, image, info


def test_sp8_metadata_is_read(sp8):
    z, image, info = sp8
    assert image.shape == (1024, 1024) and image.dtype == np.uint8
    assert info.pixel_size == pytest.approx(0.04435, rel=1e-3)  # README: 44.35 nm
    assert info.z_spacing == pytest.approx(0.1)
    assert 28 <= z <= 36  # the brightest slices (maxima reach 255) are 30-35


def test_sp8_in_focus_slice(sp8):
    z, image, info = sp8
    r = 0.5 / info.pixel_size  # 0.5 um
    est = run_with_progress(iter_estimate(image, psf_radius=r))
    op, meta = est.operator, est.operator.metadata
    # measured: 103 beads used, I = 4, 2 saturated beads excluded
    assert meta["n_beads_used"] >= 60
    assert est.beads.counts()["saturated"] >= 1
    # lateral FWHM, measured 303-312 nm across the field: a 1.4 NA confocal imaging beads
    for y, x in [(200, 200), (512, 512), (800, 800)]:
        psf = op.psf_at(y, x)
        c = psf.shape[0] // 2
        fwhm_nm = 1000 * info.pixel_size * _fwhm(psf[c])
        assert 200 < fwhm_nm < 450, (y, x, fwhm_nm)
    h = meta["heldout"]
    # measured: held-out residual 0.141 against a noise floor of 0.032 -- a misfit the
    # residual analysis (issue 4) has to explain; here it must stay a sane model
    assert h["noise_floor_mean"] < h["residual_mean"] < 0.25


def test_sp8_diagnosis_traces_the_residual(sp8):
    """The loop on measured beads: the held-out residual is traced to companions merged
    with beads and to beads of different sizes (the brightest fifth are wider), and each
    lowers the held-out error (docs/measured/sp8_confocal_beads)."""
    from napari_psfspace.core.diagnosis.loop import diagnose

    z, image, info = sp8
    d = diagnose(image, psf_radius=0.5 / info.pixel_size)
    assert {"neighbours", "bead_size"} <= set(d.added)
    for name in ("neighbours", "bead_size"):
        step = next(s for s in d.steps if s.effect == name)
        # measured: 0.0413 -> 0.0333 (neighbours), 0.0333 -> 0.0280 (bead size)
        assert step.error_after < 0.9 * step.error_before
        assert step.p_no_drop <= 0.005
    assert d.error_after < 0.75 * d.error_before
    assert d.error_after > d.noise_floor  # and it says what is left: not at the floor
    assert_figures_chain(d)


# --------------------------------------------------------------------------- every set
#: Every measured set, the slice used and the PSF radius (None: suggested from the image).
SETS = {
    "sp8": ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", 32, 0.5),
    "astigmatic": ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", 33, None),
    "starfield": ("starfield_2d/dash_starfield_uint16.tif", None, None),
    "four beads": ("single_bead_psfs/Bead_Image1_crop.tif", 24, None),
    "lattice bead": ("single_bead_psfs/pycudadecon_psf.tif", 30, None),
    "light-sheet bead": ("single_bead_psfs/BIL113_zstack_z300nm_current.tif", 10, None),
}


def _read(shared_data, name):
    path, z, radius_um = SETS[name]
    image, info = read_image(shared_data / path, index=z)
    return image, info, radius_um


@pytest.mark.parametrize("name", list(SETS))
def test_noise_model_is_plausible_or_names_its_fallback(shared_data, name):
    """On every measured set the noise model is photon transfer with a physically
    plausible gain that passed its checks, or a fallback that says which and why (the
    issue saw a gain of 4.6e-22 ADU/e- and a chi-square of 1.4e6 on an 8-bit stack)."""
    from napari_psfspace.core.beads.noise import GAIN_BOUNDS, noise_model

    image, _, _ = _read(shared_data, name)
    m = noise_model(image)
    if m.kind == "photon transfer":
        assert GAIN_BOUNDS[0] <= m.gain <= GAIN_BOUNDS[1]
        assert m.checks["slope_z"] >= 3 and m.checks["fit_chi2"] <= 25
    else:
        assert m.kind in ("constant", "unit-gain Poisson")
        assert m.note.startswith("photon transfer not possible (")
    assert np.all(m.variance(np.linspace(float(image.min()), float(image.max()), 20)) > 0)


@pytest.mark.parametrize("name", ["four beads", "lattice bead", "light-sheet bead"])
def test_single_and_few_bead_stacks_give_a_shift_invariant_psf(shared_data, name):
    """1-4 beads (data: pycudadecon MIT, pyotf Apache-2.0, BioImageAnalysisNotebooks
    CC-BY-4.0): one PSF for the whole field, said plainly."""
    from napari_psfspace.core.beads.radius import suggest_psf_radius

    image, info, _ = _read(shared_data, name)
    est = run_with_progress(iter_estimate(image, psf_radius=suggest_psf_radius(image)))
    meta = est.operator.metadata
    n = meta["n_beads_used"]
    assert 1 <= n <= 4
    assert meta["field_model"] == "shift-invariant"
    assert f"{n} usable bead" in meta["field_model_reason"]
    psf = est.operator.psf_at(*(np.array(image.shape) / 2))
    peak = np.unravel_index(np.argmax(psf), psf.shape)
    assert np.isclose(psf.sum(), 1.0)
    assert np.hypot(*(np.array(peak) - psf.shape[0] // 2)) <= 2  # a centred bead


def test_four_beads_are_too_few_to_diagnose(shared_data):
    from napari_psfspace.core.beads.detect import NoBeadsError
    from napari_psfspace.core.diagnosis.loop import diagnose

    image, _, _ = _read(shared_data, "four beads")
    with pytest.raises(NoBeadsError, match="4 kept, need at least 5"):
        diagnose(image, psf_radius=16)


def test_astigmatic_8_bit_diagnosis_numbers_agree(shared_data):
    """The 8-bit astigmatic stack (PSF-Extractor, CC-BY-4.0): a sane noise model and a
    report whose steps chain (each starts where the last kept one ended)."""
    from napari_psfspace.core.diagnosis.loop import diagnose

    image, info, _ = _read(shared_data, "astigmatic")
    d = diagnose(image, psf_radius=10)
    assert 0.5 < d.chi2_before < 5  # measured 1.25 (it was 1.4e6 on another 8-bit stack)
    assert d.noise_floor > 1e-3
    assert_figures_chain(d)
    assert d.error_after <= d.error_before


def _assert_field_is_smooth(meta):
    """At most half as many effective degrees of freedom as beads per coefficient, unless
    held-out beads showed the richer field predicts better (and the model says so)."""
    fd = meta["field_dof"]
    assert fd is not None and fd["limit"] == pytest.approx(max(3.0, fd["samples"] / 2))
    if fd["richer"]:
        assert "held-out beads show the richer field" in fd["note"]
    else:
        assert fd["max"] <= fd["limit"] * (1 + 1e-6), fd


@pytest.mark.parametrize(("z", "radius"), [(35, 10), (28, 16), (38, 14)])
def test_the_astigmatic_field_does_not_interpolate_noise(shared_data, z, radius):
    """The issue's widefield slice interpolated its 24 beads (24.0 dof); the astigmatic
    slices, 11-13 beads, measured 5.3-6.4 dof against limits of 5.5-6.5."""
    from napari_psfspace import estimate_operator

    path = SETS["astigmatic"][0]
    image, _ = read_image(shared_data / path, index=z)
    _assert_field_is_smooth(estimate_operator(image, psf_radius=radius).metadata)


def test_sp8_field_does_not_interpolate_noise(sp8):
    _, image, info = sp8
    est = run_with_progress(iter_estimate(image, psf_radius=0.5 / info.pixel_size))
    _assert_field_is_smooth(est.operator.metadata)


def test_every_slice_estimates_or_stops_with_a_message(shared_data):
    """Every 24th slice of every stack, as the command line runs it without options (the
    radius measured from the slice): a model, or one of the project's errors with a
    message, never another exception (``bench/bench_every_slice.py`` runs every slice,
    the diagnosis too). And the slices of the SP8 stack whose diagnosis once raised
    numpy's "zero-size array" (a 3 px radius leaves no ring for the secondary-peak test)."""
    import tifffile

    from napari_psfspace.core.beads.radius import suggest_psf_radius
    from napari_psfspace.core.common.errors import PsfSpaceError
    from napari_psfspace.core.diagnosis.loop import diagnose

    outcomes = {"model": 0, "stopped": 0}
    for path in sorted(shared_data.glob("*/*.tif")):
        stack = tifffile.imread(path)
        stack = stack if stack.ndim == 3 else stack[None]
        for z in range(0, len(stack), 24):  # bench_every_slice.py: every slice
            try:
                r = suggest_psf_radius(stack[z])
                run_with_progress(iter_estimate(stack[z], psf_radius=r))
                outcomes["model"] += 1
            except PsfSpaceError as exc:
                assert str(exc)
                outcomes["stopped"] += 1
    print(outcomes)
    assert outcomes["model"] >= 5 and outcomes["stopped"] >= 5
    sp8 = tifffile.imread(shared_data / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif")
    for z in (1, 62):
        try:
            d = diagnose(sp8[z], psf_radius=3.0, max_steps=2)
            assert d.verdict.headline
        except PsfSpaceError as exc:
            assert str(exc)


def test_the_suggested_radius_follows_focus_or_says_why(shared_data):
    """Every twelfth slice of the SP8 stack from its focus, every eighth of the
    astigmatic one (sources: ../shared/data/README.md; every slice: bench/RESULTS.md).
    A spot far wider than the others (an aggregate, dust) set a defocused SP8 slice's
    radius at 62 px against 20 in focus, with 9 beads left; the astigmatic stack's slice
    24 at 39 against 12. Now the confocal stack's radius stays within 1.5x of its focus
    on every slice with beads; where the astigmatic beads do spread wider (their line
    foci), the reason names the best focus and both radii."""
    from napari_psfspace.core.beads.focus import (
        SLICE_RATIO,
        best_focus_index,
        radius_against_focus,
    )
    from napari_psfspace.core.beads.radius import suggest_psf_radius
    from napari_psfspace.core.common.errors import PsfSpaceError

    for rel, strict, step in (
            ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", True, 12),
            ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", False, 8)):
        stack = tifffile.imread(shared_data / rel)
        focus = best_focus_index(stack)
        r_focus = suggest_psf_radius(stack[focus])
        for k in range(focus % step, len(stack), step):
            try:
                r = suggest_psf_radius(stack[k])
            except PsfSpaceError:
                continue  # no bead on the slice: said so by the error
            within = 1 / SLICE_RATIO <= r / r_focus <= SLICE_RATIO
            try:
                n = len(detect_beads(stack[k], r))
            except PsfSpaceError:
                n = 0
            if strict and n >= 3:
                assert within, (rel, k, r, r_focus)
            if not within:
                why = radius_against_focus(stack, k, r, focus=focus, focus_radius=r_focus)
                assert "best focus" in why and f"{r:g} px" in why, (rel, k, why)
