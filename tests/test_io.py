"""TIFF reading with the pixel size, and the default model path."""

import os
import stat

import numpy as np
import pytest

from napari_psfspace.io import default_model_path, read_image, write_tiff


def test_tiff_round_trip_keeps_pixel_size(tmp_path):
    img = np.arange(60, dtype=np.uint16).reshape(6, 10)
    write_tiff(tmp_path / "a.tif", img, pixel_size=0.065)
    back, info = read_image(tmp_path / "a.tif")
    assert np.array_equal(back, img)
    assert info.pixel_size == pytest.approx(0.065, rel=1e-6)


def test_stack_needs_a_slice(tmp_path):
    write_tiff(tmp_path / "s.tif", np.zeros((3, 8, 8), np.uint8))
    with pytest.raises(ValueError, match="--slice"):
        read_image(tmp_path / "s.tif")
    assert read_image(tmp_path / "s.tif", index=1)[0].shape == (8, 8)
    with pytest.raises(ValueError, match="out of range"):
        read_image(tmp_path / "s.tif", index=5)


def test_default_model_path_never_replaces_a_model(tmp_path):
    image = tmp_path / "beads.tif"
    first = default_model_path(image)
    assert first == tmp_path / "beads_psf_model.npz"
    first.write_bytes(b"x")
    assert default_model_path(image) == tmp_path / "beads_psf_model_2.npz"


def test_default_model_path_avoids_read_only_folders(tmp_path, monkeypatch):
    data = tmp_path / "data"
    data.mkdir()
    os.chmod(data, stat.S_IRUSR | stat.S_IXUSR)  # r-x, like ../shared/data
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    try:
        assert default_model_path(data / "beads.tif") == work / "beads_psf_model.npz"
    finally:
        os.chmod(data, stat.S_IRWXU)


def test_an_ome_tiff_gives_its_pixel_size_and_plane_spacing(tmp_path):
    """OME-XML's PhysicalSizeX and PhysicalSizeZ, in their units (µm when unstated)."""
    import tifffile

    from napari_psfspace.io import read_stack

    data = np.zeros((5, 32, 32), np.uint16)
    tifffile.imwrite(tmp_path / "a.ome.tif", data, ome=True,
                     metadata={"axes": "ZYX", "PhysicalSizeX": 0.08, "PhysicalSizeY": 0.08,
                               "PhysicalSizeZ": 0.25})
    tifffile.imwrite(tmp_path / "b.ome.tif", data, ome=True,
                     metadata={"axes": "ZYX", "PhysicalSizeX": 80, "PhysicalSizeXUnit": "nm",
                               "PhysicalSizeZ": 250, "PhysicalSizeZUnit": "nm"})
    for name in ("a.ome.tif", "b.ome.tif"):
        _, info = read_stack(tmp_path / name)
        assert info.pixel_size == pytest.approx(0.08) and info.z_spacing == pytest.approx(0.25)
    tifffile.imwrite(tmp_path / "c.ome.tif", data, ome=True, metadata={"axes": "ZYX"})
    _, info = read_stack(tmp_path / "c.ome.tif")
    assert info.pixel_size is None and info.z_spacing is None
