"""``psfspace diagnose``: report folder, refined model, summary; one-line errors."""

import json

import numpy as np
import pytest

from napari_psfspace import load_operator, simulate_beads
from napari_psfspace.cli import main
from napari_psfspace.io import write_tiff


@pytest.fixture(scope="module")
def hot_tiff(tmp_path_factory):
    image, truth = simulate_beads((384, 384), 30, seed=1, effects={"hot_pixels": 30})
    path = tmp_path_factory.mktemp("cli") / "hot.tif"
    write_tiff(path, image, pixel_size=truth.optics.pixel_size)
    return path, truth


def test_diagnose_writes_report_and_model(hot_tiff, tmp_path, capsys):
    path, truth = hot_tiff
    px = truth.optics.pixel_size
    out, model = tmp_path / "report", tmp_path / "refined.npz"
    rc = main(["diagnose", str(path), "--report", str(out), "--model", str(model),
               "--psf-radius-um", str(truth.psf_radius * px)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "baseline:" in cap.err and "final:" in cap.err  # progress lines
    assert "added:" in cap.out and "held-out error" in cap.out and "noise floor" in cap.out
    for name in ("report.md", "report.json", "residual_map_before.png",
                 "residual_map_after.png", "mean_residual_before.png",
                 "mean_residual_after.png", "residual_patches_before.png",
                 "residual_patches_after.png"):
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    run = report["run"]
    assert run["image"] == "hot.tif" and run["source"] == str(path)
    assert run["pixel_size_um"] == pytest.approx(px, rel=1e-4)
    assert run["psf_radius_px"] == pytest.approx(truth.psf_radius, rel=1e-4)
    assert report["hot_pixels"]["count"] >= 27  # 30 injected, masked at detection
    assert f"{report['hot_pixels']['count']} hot pixel(s) masked" in cap.out
    for name in report["added"]:
        assert name in cap.out
    op = load_operator(model)
    assert op.image_shape == (384, 384)
    assert op.metadata["diagnosis"]["added"] == report["added"]
    assert op.metadata["pixel_size_um"] == pytest.approx(px, rel=1e-4)
    assert np.isclose(op.psf_at(100.0, 200.0).sum(), 1.0, atol=1e-3)


@pytest.mark.parametrize("args, message", [
    (["--read-noise", "1.5"], "--read-noise needs --gain"),
    (["--gain", "2"], "together"),
    (["--psf-radius", "-3"], "--psf-radius"),
])
def test_bad_options_are_one_line_errors(hot_tiff, tmp_path, capsys, args, message):
    path, _ = hot_tiff
    rc = main(["diagnose", str(path), "--report", str(tmp_path / "r"), "--psf-radius", "14",
               *args] if "--psf-radius" not in args else
              ["diagnose", str(path), "--report", str(tmp_path / "r"), *args])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.startswith("psfspace diagnose: error:") and message in err
    assert "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


def test_report_into_a_file_and_stack_without_slice(hot_tiff, tmp_path, capsys):
    path, _ = hot_tiff
    target = tmp_path / "taken.txt"
    target.write_text("keep")
    assert main(["diagnose", str(path), "--report", str(target), "--psf-radius", "14"]) == 2
    assert "is a file" in capsys.readouterr().err and target.read_text() == "keep"
    stack = tmp_path / "stack.tif"
    write_tiff(stack, np.zeros((3, 64, 64), np.uint16))
    assert main(["diagnose", str(stack), "--report", str(tmp_path / "r")]) == 2
    assert "--slice" in capsys.readouterr().err
    assert main(["diagnose", str(stack), "--report", str(tmp_path / "r"),
                 "--psf-radius-um", "0.5", "--slice", "1"]) == 2
    assert "pixel size" in capsys.readouterr().err


def test_a_chosen_model_is_diagnosed(hot_tiff, tmp_path, capsys):
    path, truth = hot_tiff
    out = tmp_path / "r"
    rc = main(["diagnose", str(path), "--report", str(out), "--psf-radius",
               str(truth.psf_radius), "--n-psf", "2", "--smoothing", "0.5", "-q"])
    assert rc == 0, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["options"]["n_psf"] == 2 and report["options"]["smoothing"] == 0.5
