"""The QC report (``psfspace qc``, ``report/qc``): its JSON read back against the model
it came from, its page self-contained, its bad inputs named in one line.

The stack: a simulated focus series of an aberration-free microscope (NA 1.3, 600 nm,
65 nm pixels, 100 nm planes), written as an ImageJ TIFF with its sampling.
"""

import csv
import json
import re
import subprocess
import sys

import numpy as np
import pytest
import tifffile

from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.simulation.focus import immersion_index, simulate_focus_series
from napari_psfspace.core.volume import iter_estimate_operator_3d
from napari_psfspace.core.volume.measures import direct_bead_measures, model_measures
from napari_psfspace.report.qc import centre_value, pupil_theory, qc_record
from napari_psfspace.report.qc_page import write_qc_report

VOXEL = (0.1, 0.065, 0.065)  # µm


@pytest.fixture(scope="module")
def series():
    z = np.round(np.arange(-1.2, 1.2 + 0.05, 0.1), 6)
    stack, ser = simulate_focus_series((384, 384), 20, z, aberrations=None, seed=4,
                                       min_separation=50)
    return stack, ser


@pytest.fixture(scope="module")
def report(series, tmp_path_factory):
    stack, _ = series
    est = run_with_progress(iter_estimate_operator_3d(stack, psf_radius=12,
                                                      voxel_size=VOXEL))
    rec = qc_record(est, stack, voxel_size=VOXEL, sampling_from="given", na=1.3,
                    wavelength_nm=600.0, immersion_index=immersion_index(1.3),
                    source="series.tif")
    out = tmp_path_factory.mktemp("qc")
    paths = write_qc_report(rec, est, out, VOXEL)
    return est, rec, paths


def test_the_json_reads_back_against_the_model(report, series):
    est, rec, paths = report
    stack, _ = series
    back = json.loads(paths["json"].read_text(encoding="utf-8"))
    assert back == rec
    _, h, w = est.operator.image_shape
    m = model_measures(est.operator, np.array([[(h - 1) / 2, (w - 1) / 2]]))
    # the model's PSF at the centre, rounded to 0.001 nm in the file
    assert abs(back["centre"]["fwhm_lateral"]["model"] - m["fwhm_lateral"][0] * 65) <= 5e-4
    assert abs(back["centre"]["fwhm_axial"]["model"] - m["fwhm_axial"][0] * 100) <= 5e-4
    # the centre's figures: the beads' own fits taken to the centre (0.1 nm)
    direct = direct_bead_measures(stack, est)
    pos = est.patches.centers[est.basis.inliers]
    lat = centre_value(pos, direct["fwhm_lateral"], (h, w)) * 65.0
    assert abs(back["centre_fwhm_lateral_nm"] - lat) <= 0.05
    assert abs(back["centre_fwhm_axial_nm"]
               - centre_value(pos, direct["fwhm_axial"], (h, w)) * 100.0) <= 0.05
    rows_nm = [r["fwhm_lateral_nm"] for r in back["per_bead"]]
    assert np.allclose(rows_nm, np.round(direct["fwhm_lateral"] * 65.0, 1), equal_nan=True)
    assert back["sampling"] == {"pixel_size_nm": 65.0, "z_step_nm": 100.0, "from": "given"}
    assert back["beads"]["used"] == int(est.basis.inliers.sum())
    used = set(np.flatnonzero(est.beads.status == "kept"))
    assert len(back["beads"]["refused"]) == len(est.beads.status) - len(used)
    with open(paths["csv"], encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == back["beads"]["used"]
    assert {"row_px", "col_px", "fwhm_lateral_nm", "fwhm_axial_nm", "focus_plane",
            "offset_from_surface_planes"} <= set(rows[0])


def test_an_aberration_free_microscope_reads_as_its_theory_and_passes(report):
    """The simulated microscope has no aberration: the model at the centre is within 5 %
    of the pupil PSF computed at the same sampling, and every check passes."""
    _, rec, _ = report
    th = rec["theory"]["pupil_psf"]
    assert abs(rec["centre_fwhm_lateral_nm"] / th["lateral_nm"] - 1) <= 0.05
    assert abs(rec["centre_fwhm_axial_nm"] / th["axial_nm"] - 1) <= 0.05
    assert rec["passed"] is True and all(c["pass"] for c in rec["checks"])
    # Abbe's lateral width, 0.514 lambda / NA
    assert rec["theory"]["abbe"]["lateral_nm"] == pytest.approx(0.514 * 600 / 1.3, abs=0.1)


def test_the_pupil_theory_follows_the_wavelength():
    """Widths scale with the wavelength at a fixed NA (sampled finely enough)."""
    a = pupil_theory(1.2, 0.5, 1.333, (0.05, 0.03, 0.03))
    b = pupil_theory(1.2, 0.6, 1.333, (0.06, 0.036, 0.036))
    assert b["lateral_nm"] / a["lateral_nm"] == pytest.approx(1.2, rel=0.03)
    assert b["axial_nm"] / a["axial_nm"] == pytest.approx(1.2, rel=0.03)


def test_the_page_is_self_contained(report):
    _, _, paths = report
    page = paths["html"].read_text(encoding="utf-8")
    assert "<script" not in page and "<link" not in page
    assert not re.search(r"https?://", page)
    srcs = re.findall(r'src="([^"]*)"', page)
    assert len(srcs) == 10 and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert paths["html"].stat().st_size < 5e6


def _tiff(path, stack, pixel_um, dz_um):
    tifffile.imwrite(path, stack, imagej=True, resolution=(1 / pixel_um, 1 / pixel_um),
                     metadata={"unit": "um", "spacing": dz_um, "axes": "ZYX"})


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "napari_psfspace.cli", *args],
                          capture_output=True, text=True, timeout=600)


def test_the_cli_reads_the_sampling_from_the_file_and_writes_three_files(series, tmp_path):
    stack, _ = series
    _tiff(tmp_path / "s.tif", stack, 0.065, 0.1)
    got = _cli("qc", str(tmp_path / "s.tif"), "-o", str(tmp_path / "out"), "--psf-radius",
               "12", "--diagnose", "-q")
    assert got.returncode == 0, got.stderr
    rec = json.loads((tmp_path / "out" / "qc.json").read_text(encoding="utf-8"))
    assert rec["sampling"] == {"pixel_size_nm": 65.0, "z_step_nm": 100.0, "from": "file"}
    # no NA nor wavelength: no theory, and no check against it (the others still judged)
    assert rec["theory"] is None
    assert [c["name"] for c in rec["checks"]] == ["ellipticity",
                                                  "focal surface rise / axial FWHM"]
    page = (tmp_path / "out" / "qc.html").read_text(encoding="utf-8")
    assert "no theory" in page
    # the best-focus slice's diagnosis: its verdict and the effects it added
    d = rec["diagnosis"]
    assert d["headline"].startswith("Verdict:") and d["headline"] in page
    assert isinstance(d["added"], list) and 0 <= d["slice"] < stack.shape[0]
    assert {p.name for p in (tmp_path / "out").iterdir()} == {"qc.html", "qc.json",
                                                               "qc_beads.csv"}


def test_the_cli_reads_an_ome_zarr_stack_and_its_voxel_size(series, tmp_path):
    from test_io import _ome_zarr

    stack, _ = series
    _ome_zarr(tmp_path / "s.zarr", stack, "zyx", (0.1, 0.065, 0.065), ("micrometer",) * 3)
    got = _cli("qc", str(tmp_path / "s.zarr"), "-o", str(tmp_path / "out"), "--psf-radius",
               "12", "-q")
    assert got.returncode == 0, got.stderr
    rec = json.loads((tmp_path / "out" / "qc.json").read_text(encoding="utf-8"))
    assert rec["sampling"] == {"pixel_size_nm": 65.0, "z_step_nm": 100.0, "from": "file"}
    assert rec["source"] == "s.zarr"


def test_a_stack_too_short_for_any_axial_profile_gives_a_report_and_no_warning(series,
                                                                             tmp_path):
    """Three planes: no bead's half maximum is crossed in z, so no focus, no axial width,
    no focal surface; the report says so (null), with no NaN and no warning."""
    stack, _ = series
    mid = stack.shape[0] // 2
    _tiff(tmp_path / "short.tif", stack[mid - 1:mid + 2], 0.065, 0.1)
    got = _cli("qc", str(tmp_path / "short.tif"), "-o", str(tmp_path / "out"),
               "--psf-radius", "12", "-q")
    assert got.returncode == 0 and "Warning" not in got.stderr, got.stderr
    rec = json.loads((tmp_path / "out" / "qc.json").read_text(encoding="utf-8"))
    assert rec["centre_fwhm_axial_nm"] is None
    assert rec["focal_surface"]["centre_plane"] is None


def test_bad_inputs_are_one_line_before_any_work(tmp_path):
    missing = _cli("qc", str(tmp_path / "none.tif"), "-o", str(tmp_path / "o"))
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1
    assert "none.tif" in missing.stderr
    (tmp_path / "file").write_text("x")
    flat = tmp_path / "flat.tif"
    _tiff(flat, np.zeros((3, 32, 32), np.uint16), 0.1, 0.2)
    as_file = _cli("qc", str(flat), "-o", str(tmp_path / "file"))
    assert as_file.returncode == 2 and "-o" in as_file.stderr and "folder" in as_file.stderr
    assert as_file.stderr.count("\n") == 1


def test_the_centre_value_is_the_planes_at_the_centre_despite_an_outlier():
    rng = np.random.default_rng(2)
    pos = rng.uniform(0, 400, (30, 2))
    u = (pos[:, 0] - 199.5) / (0.5 * np.hypot(400, 400))
    values = 250.0 + 30.0 * u + rng.normal(0, 2.0, 30)
    values[3] = 900.0  # a bead read far off
    # least squares of 29 values of sd 2 on 3 terms: sd sqrt(3 / 29) = 0.64 at the centre;
    # 4 times that bounds the draw
    assert abs(centre_value(pos, values, (400, 400)) - 250.0) <= 4 * 2.0 * np.sqrt(3 / 29)
    assert centre_value(pos[:4], values[4:8], (400, 400)) == np.median(values[4:8])
    assert np.isnan(centre_value(pos[:2], [np.nan, np.nan], (400, 400)))
