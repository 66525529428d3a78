"""The npe2 manifest is valid and its contributions import and run headless."""

import importlib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_root_manifest_is_the_packaged_one():
    root = ROOT / "napari.yaml"
    packaged = ROOT / "src" / "napari_psfspace" / "napari.yaml"
    assert root.read_text() == packaged.read_text()


def test_manifest_validates_with_imports():
    npe2 = pytest.importorskip("npe2")
    pm = npe2.PluginManifest.from_file(ROOT / "src" / "napari_psfspace" / "napari.yaml")
    pm.validate_imports()
    assert pm.name == "napari-psfspace"
    assert pm.contributions.sample_data


def test_every_command_is_declared_once():
    yaml = pytest.importorskip("yaml")
    manifest = yaml.safe_load((ROOT / "napari.yaml").read_text())
    ids = [c["id"] for c in manifest["contributions"]["commands"]]
    assert len(ids) == len(set(ids)), sorted(i for i in ids if ids.count(i) > 1)


def test_sample_data_is_a_bead_field_with_truth():
    from napari_psfspace._sample_data import simulated_beads

    layers = simulated_beads()
    (image, img_kw, img_type), (points, _, pts_type) = layers
    assert (img_type, pts_type) == ("image", "points")
    assert image.shape == (768, 768) and image.dtype == np.uint16
    assert points.shape[1] == 2 and len(points) >= 60
    assert img_kw["metadata"]["psf_radius"] > 3
    mod = importlib.import_module("napari_psfspace._sample_data")
    assert callable(mod.simulated_beads)


def test_the_focus_series_sample_is_a_calibrated_stack():
    from napari_psfspace._sample_data import SERIES_Z_UM, simulated_focus_series

    ((stack, kwargs, kind),) = simulated_focus_series()
    assert kind == "image" and stack.shape == (len(SERIES_Z_UM), 512, 512)
    assert kwargs["scale"][0] == pytest.approx(SERIES_Z_UM[1] - SERIES_Z_UM[0])
    assert kwargs["metadata"]["psf_radius"] > 3 and kwargs["metadata"]["pixel_size_um"] > 0
