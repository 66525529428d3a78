"""Real camera data: low counts, 8-bit images, hot pixels, known bead size, few beads.

Scenes come from the seeded family of :mod:`napari_psfspace.core.simulation.scene_set`: the optics,
camera and slide are drawn per seed, so nothing here holds for one setting only.
"""

import numpy as np
import pytest

import napari_psfspace as ps
from napari_psfspace.core.beads.noise import noise_model
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.model.fewbeads import FEW_BEADS
from napari_psfspace.core.simulation import FieldAberrations, Optics
from napari_psfspace.core.simulation.metrics import evaluate_against_truth, grid_errors
from napari_psfspace.core.simulation.scene_set import LOW_COUNT_8BIT, isolated, match, random_scene

LOW_COUNT = LOW_COUNT_8BIT


@pytest.mark.parametrize("seed", range(6))
def test_detection_on_8_bit_low_count_fields(seed):
    image, truth, params = random_scene(seed, **LOW_COUNT)
    assert image.dtype == np.uint8
    r = truth.psf_radius
    beads = ps.detect_beads(image, r)
    found, real = match(beads.positions, truth.positions, max(1.5, r / 3))
    iso = isolated(truth.positions, r)
    # bench over 20 seeds (bench/bench_camera.py): recall 100 %, no false detection
    # (before the noise floor: 617 detections on one such field, 93 % false)
    assert found[iso].mean() >= 0.95
    assert (~real).mean() <= 0.05


@pytest.mark.parametrize("seed", range(6))
def test_noise_model_is_sane_or_names_its_fallback(seed):
    image, truth, params = random_scene(seed, **LOW_COUNT)
    m = noise_model(image)
    if m.kind == "photon transfer":
        # measured over the scene set: gains within 0.8-1.2 x the truth where the checks pass
        assert 0.5 <= m.gain / params["gain"] <= 2.0
        assert m.checks["slope_z"] >= 3
    else:
        assert m.kind in ("constant", "unit-gain Poisson") and "photon transfer not " in m.note
    # never below the rounding of the integers, anywhere above the image's minimum
    assert np.all(m.variance(np.linspace(int(image.min()), 255, 9)) >= 1 / 12 - 1e-12)


def test_a_flat_8_bit_export_falls_back_and_says_why():
    """The issue's case: an 8-bit export with a background of a few ADU and almost no
    visible noise (gain 0.02 ADU/e-); photon transfer used to report a gain of 1e-22
    ADU/e-. Its background noise is below the integers' rounding: a named fallback."""
    image, _, params = random_scene(14, **{**LOW_COUNT, "gain": 0.02})
    m = noise_model(image)
    assert m.kind in ("constant", "unit-gain Poisson")
    assert "photon transfer not possible" in m.note
    assert m.gain in (0.0, 1.0) and m.min_variance == pytest.approx(1 / 12)
    assert np.all(m.variance(np.arange(int(image.min()), 256)) >= 1 / 12)


@pytest.fixture(scope="module")
def field_768():
    """768 x 768, 90 beads, moderate aberrations, 100 nm pixels."""
    return ps.simulate_beads((768, 768), 90, aberrations="moderate",
                             optics=Optics(pixel_size=0.1), seed=0)


def _field_error(image, truth, **kwargs) -> float:
    est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius, **kwargs))
    return evaluate_against_truth(est.operator, truth)["aligned"]["mean"], est


@pytest.mark.parametrize("fraction", [0.001])  # 0.05 % too: bench/bench_camera.py
def test_hot_pixels_leave_the_field_error_alone(field_768, fraction):
    """sCMOS hot pixels without dark-frame correction: each 1-5 x the brightest bead."""
    image, truth = field_768
    clean, _ = _field_error(image, truth)
    hot, t = ps.simulate_beads((768, 768), 90, aberrations="moderate",
                               optics=Optics(pixel_size=0.1), seed=0,
                               effects={"hot_pixels": (fraction, (1.0, 5.0))})
    where = t.effects["hot_pixel_positions"]
    err, est = _field_error(hot, truth)
    # measured: 0.0454 clean; 0.0454 (294 of 295 hot pixels found) and 0.0288 (588 of
    # 590; lower only because the outlier test kept 3 more corner beads); the issue's
    # bound is 1.2 x (before: 0.81 against 0.033 on 1024^2)
    assert err <= 1.2 * clean
    assert len(est.beads.hot_pixels) >= 0.95 * len(where)
    assert est.operator.metadata["hot_pixels"]["count"] == len(est.beads.hot_pixels)
    assert "hot pixel(s) masked" in est.beads.summary()


def test_known_bead_size_is_divided_out(field_768):
    """200 nm beads at 100 nm pixels: the field error against the point PSF is within
    1.3 x that of point beads once ``bead_diameter`` is given."""
    image, truth = field_768
    point, _ = _field_error(image, truth)
    beads, t = ps.simulate_beads((768, 768), 90, aberrations="moderate",
                                 optics=Optics(pixel_size=0.1), seed=0,
                                 effects={"bead_size": 0.2})
    plain, _ = _field_error(beads, t)
    fixed, est = _field_error(beads, t, bead_diameter=2.0)
    # measured: point 0.0454, 200 nm beads 0.1075 uncorrected, 0.0385 corrected (0.85 x;
    # signal up to 0.434 cycles/px, gain at most 2.1)
    assert plain > 2 * point
    assert fixed <= 1.3 * point
    corr = est.operator.metadata["bead_correction"]
    assert corr["diameter_px"] == 2.0 and 0.38 <= corr["band_px"] <= 0.48  # cutoff 0.433
    assert "warning" not in corr
    assert est.operator.metadata["bead_diameter_px"] == 2.0


# the common bead at its usual pixel, and one too big for the optics; 0.1 um at 0.13 um
# and the other sizes: bench/bench_camera.py's table
@pytest.mark.parametrize(("d_um", "pixel"), [(0.2, 0.065), (0.5, 0.13)])
def test_bead_sizes_and_pixels_of_the_family(d_um, pixel):
    """100-500 nm beads at 65-130 nm pixels: the correction never makes the PSF worse,
    and says when the bead is too big for the optics."""
    image, truth = ps.simulate_beads((512, 512), 40, aberrations="moderate",
                                     optics=Optics(pixel_size=pixel), seed=1,
                                     effects={"bead_size": d_um})
    plain, _ = _field_error(image, truth)
    fixed, est = _field_error(image, truth, bead_diameter=d_um / pixel)
    # measured: 0.082 -> 0.072, 0.122 -> 0.071, 0.423 -> 0.206 (the sphere's first zero
    # at 0.26 cycles/px lies inside the band: what was there is lost, and it says so)
    assert fixed < plain
    corr = est.operator.metadata["bead_correction"]
    assert ("warning" in corr) == (corr["first_zero_px"] < corr["band_px"])
    if d_um == 0.5:
        assert "large for these optics" in corr["warning"]


def test_bead_diameter_is_checked():
    image, truth = ps.simulate_beads((256, 256), 12, seed=0)
    with pytest.raises(ValueError, match="`bead_diameter`.*larger than `psf_radius`"):
        ps.estimate_operator(image, psf_radius=truth.psf_radius, bead_diameter=200)
    with pytest.raises(ValueError, match="`bead_diameter`"):
        ps.estimate_operator(image, psf_radius=truth.psf_radius, bead_diameter=-1)


def _varying_field(n_beads, seed):
    """A PSF that changes strongly across the field (sharp on one side, defocus rings on
    the other, a tilted coverslip), high NA: the issue's few-beads case."""
    aberr = FieldAberrations({4: (0.15, 0.25, 0.0), 11: (0.05,)})
    return ps.simulate_beads((512, 512), n_beads, aberrations=aberr,
                             optics=Optics(na=1.46, wavelength=0.6, pixel_size=0.08),
                             min_separation=60, amplitude=(4e4, 8e4), seed=seed)


# 5 beads: the few-bead models; 12: the thin-plate field (8 was the same branch as 5)
@pytest.mark.parametrize(("n_beads", "seed"), [(5, 0), (12, 2)])
def test_few_beads_give_the_richest_model_they_support(n_beads, seed):
    image, truth = _varying_field(n_beads, seed)
    err, est = _field_error(image, truth)
    meta = est.operator.metadata
    used = meta["n_beads_used"]
    si = evaluate_against_truth(est.operator, truth)["shift_invariant"]["mean"]
    if used <= FEW_BEADS:
        assert meta["field_model"] in ("shift-invariant", "affine", "thin-plate")
        assert f"{used} usable beads" in meta["field_model_reason"]
        assert set(meta["few_beads_loo_errors"]) >= {"shift-invariant"}
        assert meta["heldout"]["n_beads"] == used  # every bead left out once
    else:
        assert meta["field_model"] == "thin-plate"
    # measured: 0.234 (affine, I=3), 0.238 (affine, I=2), 0.121 (12 beads: thin-plate)
    # against 0.394 for the best single PSF
    assert err < 0.75 * si


def test_one_or_two_beads_give_one_psf_and_say_why():
    image, truth = ps.simulate_beads((256, 256), 1, seed=0)
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius)
    assert op.n_psf == 1 and op.metadata["field_model"] == "shift-invariant"
    assert "1 usable bead, fewer than 5: one PSF: too few beads to map the field" in (
        op.metadata["field_model_reason"])
    assert np.isclose(op.psf_at(10.0, 200.0).sum(), 1.0)
    assert np.allclose(op.psf_at(10.0, 200.0), op.psf_at(200.0, 10.0))


def test_four_beads_map_no_field_and_the_maps_say_so():
    """Four beads spread over a strongly varying field: below the held-out minimum the
    model is one PSF (never a field fitted through three beads at a time), its reason
    and its FWHM line say the field was not mapped, and no corner FWHM is quoted."""
    from napari_psfspace.core.common.measures import field_fwhm, fwhm_line
    from napari_psfspace.core.model.fewbeads import FIELD_MIN_BEADS, TOO_FEW, one_psf_note

    image, truth = _varying_field(4, 1)
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius)
    meta = op.metadata
    assert meta["n_beads_used"] < FIELD_MIN_BEADS
    assert op.n_psf == 1 and meta["field_model"] == "shift-invariant"
    assert TOO_FEW in meta["field_model_reason"]
    line = fwhm_line(field_fwhm(op), 0.08, one_psf=one_psf_note(meta))
    assert line.endswith(TOO_FEW) and "corners" not in line
    # the richer field is scored and named (on this tilted field it predicts the left-out
    # beads better), and the user can ask for it
    loo = meta["few_beads_loo_errors"]
    if loo["affine, I=2"] < loo["shift-invariant"]:
        assert "`n_psf` = 2 asks for it" in meta["field_model_reason"]
        asked = ps.estimate_operator(image, psf_radius=truth.psf_radius, n_psf=2)
        assert asked.n_psf == 2 and asked.metadata["field_model"] == "affine"


def test_diagnose_by_leaving_one_bead_out_from_five_beads():
    image, truth = _varying_field(6, 3)
    d = diagnose(image, psf_radius=truth.psf_radius)
    assert d.options["leave_one_bead_out"]
    assert d.options["folds"] == len(d.crossfit_before.bead_index)
    assert 5 <= d.options["folds"] <= 6
    assert np.isfinite(d.error_before) and d.error_before > 0
    few, t = ps.simulate_beads((256, 256), 3, seed=2)
    with pytest.raises(ps.NoBeadsError, match="at least 5.*leave-one-bead-out"):
        diagnose(few, psf_radius=t.psf_radius)


def _with_a_faint_spot(seed: int, fraction: float):
    """5-8 bright beads of a seeded optics, and one spot of ``fraction`` of the median
    bead's photons (a speck of dust, a noise bump): the image with it and without it
    (the same scene and layout)."""
    rng = np.random.default_rng([seed, 77])
    n = int(rng.integers(5, 9))
    optics = Optics(na=float(rng.uniform(0.8, 1.45)), wavelength=float(rng.uniform(0.5, 0.68)),
                    pixel_size=float(rng.uniform(0.06, 0.12)))
    photons = rng.uniform(4e4, 1.2e5, n + 1)
    photons[-1] = fraction * np.median(photons[:-1])
    kw = dict(aberrations=["moderate", "strong", "none"][seed % 3], optics=optics,
              background=(2, 6), gain=1.0, read_noise=1.0, seed=seed)
    with_spot = ps.simulate_beads((384, 384), n + 1, bead_photons=photons, **kw)
    without = ps.simulate_beads((384, 384), n + 1, bead_photons=np.r_[photons[:-1], 0], **kw)
    return with_spot, without


def test_a_faint_detection_never_shapes_a_few_bead_model():
    """A detection at 1 % of the median bead's flux is left out as faint (and says why);
    the field error is that of the image without it. Without the rule it was used in 6 of
    the first 8 seeds, the error up to 1.6 x."""
    tested = 0
    for seed in range(6):
        (image, truth), (clean, _) = _with_a_faint_spot(seed, 0.01)
        est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius))
        spot = truth.positions[-1]
        dist = np.hypot(*(est.beads.positions - spot).T)
        j = int(np.argmin(dist))
        assert dist[j] < 3  # it is detected
        meta = est.operator.metadata
        used = np.asarray(meta["bead_positions"])
        assert np.hypot(*(used - spot).T).min() > 3  # and never used
        if est.beads.status[j] == "border":
            continue
        tested += 1
        assert est.beads.status[j] == "faint"
        left = [b for b in meta["left_out"]["beads"] if b["status"] == "faint"]
        assert any("too faint to shape the PSF" in b["why"] for b in left)
        ref = run_with_progress(iter_estimate(clean, psf_radius=truth.psf_radius)).operator
        # the field error on a 5 x 5 grid (aligned), with and without the spot
        err, ref = (float(grid_errors(op, truth, n=5).mean()) for op in (est.operator, ref))
        assert err <= 1.2 * ref  # measured: 0.994-1.022 (8 x 8 grid)
    print(f"{tested} of 6 away from the border")
    assert tested >= 4
