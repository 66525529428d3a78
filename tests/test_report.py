"""The diagnosis report: files, documented JSON fields, readable text, figures."""

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from diagnosis_checks import assert_figures_chain
from napari_psfspace import simulate_beads
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.report import (
    FIGURES,
    colorize,
    diverging_grey,
    residual_map,
    to_jsonable,
    write_report,
)

DOC = Path(__file__).resolve().parents[1] / "docs" / "report-format.md"


def _strict_json(path):
    def refuse(name):
        raise AssertionError(f"{name} in {path}")

    return json.loads(Path(path).read_text(encoding="utf-8"), parse_constant=refuse)


@pytest.fixture(scope="module")
def hot(tmp_path_factory):
    """A diagnosis of an image with hot pixels and its report (run once)."""
    image, truth = simulate_beads((384, 384), 30, seed=1, effects={"hot_pixels": 30})
    d = diagnose(image, psf_radius=truth.psf_radius)
    out = tmp_path_factory.mktemp("report")
    md = write_report(d, out, image_name="hot.tif", pixel_size=0.065, extra={"note": "x"})
    return d, out, md


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """A diagnosis that adds nothing (no candidate effect) and its report."""
    image, truth = simulate_beads((384, 384), 25, seed=3)
    d = diagnose(image, psf_radius=truth.psf_radius, effects=[])
    out = tmp_path_factory.mktemp("plain")
    return d, out, write_report(d, out / "new" / "folder")


def test_files_exist_and_figures_are_images(hot):
    import imageio.v3 as iio

    d, out, md = hot
    assert md == out / "report.md"
    for name in ("report.md", "report.json", *FIGURES):
        assert (out / name).is_file(), name
    for when in ("before", "after"):
        rgb = iio.imread(out / f"residual_map_{when}.png")
        assert rgb.ndim == 3 and rgb.shape[2] == 3 and min(rgb.shape[:2]) >= 256
        mean = iio.imread(out / f"mean_residual_{when}.png")
        assert mean.ndim == 3 and mean.shape[0] >= 3 * d.operator.psf_size
        assert iio.imread(out / f"residual_patches_{when}.png").ndim == 3
    assert not list(out.glob(".*tmp"))  # atomic writes leave no temporary file


def test_json_has_the_documented_fields(hot):
    d, out, _ = hot
    data = _strict_json(out / "report.json")  # no NaN / Infinity
    doc = DOC.read_text(encoding="utf-8")
    documented = set(re.findall(r"^\| `([a-z_0-9]+)`", doc, flags=re.M))
    for key in data:
        assert key in documented, f"report.json field {key!r} not in {DOC.name}"
    for key in set(data["run"]) - {"note"}:  # "note": the caller's extra
        assert key in documented, f"run.{key} not in {DOC.name}"
    for key in data["steps"][0]:
        assert key in documented, f"steps[].{key} not in {DOC.name}"
    assert data["format"] == "napari-psfspace/diagnosis-report" and data["version"] == 1
    run = data["run"]
    assert run["image"] == "hot.tif" and run["image_shape"] == [384, 384]
    assert run["pixel_size_um"] == 0.065 and run["note"] == "x"
    assert run["psf_radius_um"] == pytest.approx(0.065 * d.context.psf_radius)
    assert run["version"] and run["date"]
    assert data["added"] == d.added
    assert data["error_before"] == pytest.approx(d.error_before)
    assert data["error_after"] == pytest.approx(d.error_after)
    assert data["noise_floor"] == pytest.approx(d.noise_floor)
    assert len(data["steps"]) == len(d.steps) and data["steps"][0]["effect"] is None
    assert data["noise_model"]["source"] == d.noise_source
    assert set(data["analysis_before"]) == set(d.analysis_before.tests)
    assert set(data["figures"]) == set(FIGURES)
    for name in d.added:
        assert data["effects"][name]


def test_markdown_says_what_was_found(hot):
    d, _, md = hot
    text = md.read_text(encoding="utf-8")
    for s in d.steps[1:]:
        assert f"| {s.effect} |" in text
    found = text.split("## What was found")[1].split("## ")[0]
    # the verdict first: whether the model explains its own held-out beads
    assert found.strip().splitlines()[0] == f"**{d.verdict.headline}**"
    if d.added:
        for name in d.added:
            assert f"**{name}**" in found
        assert f"{d.error_before:.4g} -> {d.error_after:.4g}" in found
    elif d.verdict.level == "not explained":
        assert "No effect was added" in found and "No effect was found" not in found
    else:
        assert "No effect was found" in found
    assert_figures_chain(d)
    assert "noise floor" in found and f"{d.noise_floor:.4g}" in found
    assert d.noise_source in text
    for name in FIGURES:
        assert f"({name})" in text


def test_hot_pixels_are_masked_and_named(hot):
    """The 30 injected hot pixels are found at detection (narrower than the optics can
    form), masked before any fit, and named in the report's findings and its JSON."""
    d, out, md = hot
    assert 28 <= len(d.hot_pixels) <= 32  # measured: 30
    found = md.read_text(encoding="utf-8").split("## What was found")[1].split("## ")[0]
    assert f"**Hot pixels**: {len(d.hot_pixels)} pixel(s)" in found
    data = _strict_json(out / "report.json")
    assert data["hot_pixels"]["count"] == len(d.hot_pixels)
    assert d.context.pixel_mask[tuple(d.hot_pixels.T)].all()
    assert "outlier_pixels" not in d.added  # nothing left for the loop to find


def test_each_step_starts_where_the_last_kept_one_ended(hot):
    """The numbers of the report agree with each other: a step's "before" is the model
    as it stands (the last kept step's "after", the baseline's at first), and the
    diagnosis's final error is the last kept step's."""
    d, _, _ = hot
    current = (d.steps[0].error_after, d.steps[0].chi2_after)
    pre = [s for s in d.steps if s.stage == "before the fit"]
    assert [s.effect for s in pre] == ["hot_pixels"] and pre[0].accepted
    # masking before the fit: the image as recorded is its before, the baseline its after
    assert (pre[0].error_after, pre[0].chi2_after) == current
    assert pre[0].error_before > pre[0].error_after
    assert pre[0].statistic["before"] == len(d.hot_pixels) > 0
    assert pre[0].statistic["after"] == 0
    for s in d.steps[1:]:
        if s.stage == "before the fit":
            continue
        assert (s.error_before, s.chi2_before) == current
        if s.accepted:
            current = (s.error_after, s.chi2_after)
    assert (d.error_after, d.chi2_after) == current
    assert d.error_before == d.steps[0].error_before


def test_an_added_effect_reads_as_added(hot, tmp_path):
    """Whatever the loop decided on this image: a kept step is reported as added."""
    d, _, _ = hot
    steps = [d.steps[0], dataclasses.replace(d.steps[-1], accepted=True)]
    fake = dataclasses.replace(d, steps=steps)
    text = write_report(fake, tmp_path).read_text(encoding="utf-8")
    assert f"**{steps[1].effect}**" in text and "No effect was found" not in text
    assert "| kept |" in text


def test_no_effect_says_so_plainly(plain):
    d, out, md = plain
    assert d.added == []
    text = md.read_text(encoding="utf-8")
    assert "No effect was found" in text and "plain model is kept" in text
    data = _strict_json(md.parent / "report.json")
    assert data["added"] == [] and data["relative_drop"] == 0.0
    assert data["run"]["pixel_size_um"] is None and data["run"]["psf_radius_um"] is None


def test_report_into_a_file_is_refused(plain, tmp_path):
    d, _, _ = plain
    target = tmp_path / "a_file"
    target.write_text("keep me")
    with pytest.raises(ValueError, match="is a file"):
        write_report(d, target)
    assert target.read_text() == "keep me"


def test_residual_map_paints_disks_largest_on_top():
    m = residual_map([[10.0, 10.0], [12.0, 12.0], [90.0, 50.0]], [1.0, 2.0, np.nan],
                     (100, 60), cells=10, radius=1.0)
    assert m.shape == (10, 6)  # square cells of 10 px
    assert m[1, 1] == 2.0  # the larger value shows where disks overlap
    assert np.isnan(m[9, 5]) and np.isnan(m[5, 3])  # NaN value and empty cells left out
    assert np.nansum(m > 0) >= 2


def test_colour_ramps():
    rgb = colorize(np.array([[0.0, 1.0, np.nan, 5.0]]), 0.0, 1.0)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 4, 3)
    assert tuple(rgb[0, 0]) == (68, 1, 84) and tuple(rgb[0, 1]) == (253, 231, 37)
    assert tuple(rgb[0, 3]) == tuple(rgb[0, 1])  # clipped
    assert len(set(rgb[0, 2])) == 1  # grey where no data
    g = diverging_grey(np.array([-9.0, 0.0, 9.0]), 3.0)
    assert g.tolist() == [0, 128, 255]


def test_to_jsonable():
    out = to_jsonable({"a": np.float32(1.5), "b": np.array([1, 2]), "c": float("nan"),
                       1: (np.int64(3), np.inf), "d": np.bool_(True)})
    assert out == {"a": 1.5, "b": [1, 2], "c": None, "1": [3, None], "d": True}
    json.dumps(out, allow_nan=False)


def test_an_assumed_noise_model_qualifies_the_floor(tmp_path):
    """An 8-bit export whose background noise is below the integers' rounding: the noise
    model is a named fallback, and the report says its floor is only indicative."""
    from napari_psfspace.core.simulation.scene_set import LOW_COUNT_8BIT, random_scene
    from napari_psfspace.report import summary_text

    image, truth, _ = random_scene(14, **{**LOW_COUNT_8BIT, "gain": 0.02})
    d = diagnose(image, psf_radius=truth.psf_radius, effects=[])
    assert d.context.noise.kind in ("constant", "unit-gain Poisson")
    assert "noise model assumed" in summary_text(d)
    text = write_report(d, tmp_path).read_text(encoding="utf-8")
    found = text.split("## What was found")[1].split("## ")[0]
    assert "The noise model is assumed" in found and "only indicative" in found
    assert "Fallback (" in text.split("## Noise model")[1]


def test_report_says_how_much_vignetting_would_have_been_seen(plain):
    d, _, md = plain
    text = Path(md).read_text(encoding="utf-8")
    loss = d.analysis_before.tests["amplitude_field"].detail["min_corner_loss"]
    # 25 beads of a 3x brightness spread: only a deep fall-off would stand out
    assert 0.2 < loss < 1.0
    assert "**Vignetting**: none found" in text and f"{100 * loss:.0f} %" in text


def test_a_model_that_does_not_explain_its_beads_says_so_first(tmp_path):
    """One PSF for a strongly varying field of bright beads: the held-out error is about
    250 times its floor (measured 0.077 against 0.0003). The report's first line, the
    command line's summary and report.json say the model does not explain its own
    held-out beads, with what was tested; nowhere "no effect was found"."""
    from napari_psfspace.report import summary_text

    image, truth = simulate_beads((512, 512), 50, aberrations="strong", seed=3,
                                  amplitude=(2e5, 5e5))
    d = diagnose(image, psf_radius=truth.psf_radius, n_psf=1, effects=[])
    v = d.verdict
    assert v.level == "not explained" and v.ratio > 5
    assert "DOES NOT EXPLAIN ITS OWN HELD-OUT BEADS" in v.headline and v.hints
    md = write_report(d, tmp_path).read_text(encoding="utf-8")
    found = md.split("## What was found")[1].split("## ")[0]
    assert found.strip().splitlines()[0] == f"**{v.headline}**"
    assert "No effect was found" not in md and "No effect was added" in found
    assert summary_text(d).splitlines()[0] == v.headline
    data = _strict_json(tmp_path / "report.json")
    assert data["verdict"]["level"] == "not explained"
    assert_figures_chain(d)


@pytest.mark.parametrize("seed", [2, 4])
def test_family_reports_chain(seed):
    """Every line's figures chain on scenes of the family with an effect to find (column
    offsets), as on the measured sets (tests/test_measured.py)."""
    from napari_psfspace.core.simulation.scene_set import random_scene

    image, truth, _ = random_scene(seed, shape=(384, 384), n_beads=(40, 60),
                                   effects={"column_offsets": 6.0})
    d = diagnose(image, psf_radius=truth.psf_radius, max_steps=3)
    assert len(d.steps) >= 2  # something was tried
    assert_figures_chain(d)


def test_an_error_below_its_noise_floor_is_called_indicative():
    """A noise model that overstates the noise (camera values giving 60 e- of read noise
    against 1.5) sets the floor far above what the beads leave: the verdict says the
    floor is overstated rather than calling the model better than noise allows. With
    the image's own photon transfer the same scene reads near 1 and says nothing."""
    from napari_psfspace.core.diagnosis.verdict import BELOW_FLOOR_RATIO

    image, truth = simulate_beads((384, 384), 40, aberrations="none", seed=5)
    own = diagnose(image, psf_radius=truth.psf_radius, max_steps=0)
    given = diagnose(image, psf_radius=truth.psf_radius, max_steps=0, gain=1.0,
                     offset=100.0, read_noise=60.0)
    # measured: 0.95 and 0.27
    assert own.verdict.ratio >= BELOW_FLOOR_RATIO
    assert "below its noise floor" not in own.verdict.headline
    assert given.verdict.ratio < BELOW_FLOOR_RATIO
    assert "below its noise floor" in given.verdict.headline
    assert "camera values given" in given.verdict.headline
    assert any("gain" in h for h in given.verdict.hints)
