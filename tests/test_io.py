"""TIFF reading with the pixel size, and the default model path."""


import numpy as np
import pytest

from napari_psfspace.io import read_image, write_tiff


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


def _ome_zarr(path, data, axes, scale, units, version="0.4"):
    """An OME-Zarr image written with zarr alone (v2 store for NGFF 0.4, v3 for 0.5)."""
    zarr = pytest.importorskip("zarr", minversion="3", reason="writing the test images "
                               "takes zarr 3")
    fmt = 2 if version == "0.4" else 3
    root = zarr.open_group(str(path), mode="w", zarr_format=fmt)
    arr = root.create_array("0", shape=data.shape, dtype=data.dtype)
    arr[...] = data
    ms = {"version": version, "axes": [{"name": a, "type": "space" if a in "zyx" else
                                         ("time" if a == "t" else "channel"),
                                         **({"unit": u} if u else {})}
                                        for a, u in zip(axes, units, strict=True)],
          "datasets": [{"path": "0", "coordinateTransformations": [
              {"type": "scale", "scale": list(scale)}]}]}
    if fmt == 2:
        root.attrs["multiscales"] = [ms]
    else:
        root.attrs["ome"] = {"version": version, "multiscales": [ms]}


def test_an_ome_zarr_gives_its_stack_pixel_size_and_plane_spacing(tmp_path):
    """NGFF 0.4 (zarr v2) and 0.5 (v3): the (Z, Y, X) array and the scale in µm, from
    micrometre or nanometre axes; singleton t and c dropped, a second channel refused."""
    from napari_psfspace.io import read_stack

    data = np.arange(3 * 8 * 10, dtype=np.uint16).reshape(1, 1, 3, 8, 10)
    _ome_zarr(tmp_path / "a.zarr", data, "tczyx", (1, 1, 0.2, 0.065, 0.065),
              (None, None, "micrometer", "micrometer", "micrometer"))
    _ome_zarr(tmp_path / "b.zarr", data[0, 0], "zyx", (200, 65, 65),
              ("nanometer",) * 3, version="0.5")
    for name in ("a.zarr", "b.zarr"):
        stack, info = read_stack(tmp_path / name)
        assert np.array_equal(stack, data[0, 0]) and info.axes == "ZYX"
        assert info.pixel_size == pytest.approx(0.065) and info.z_spacing == pytest.approx(0.2)
    _ome_zarr(tmp_path / "c.zarr", np.zeros((2, 3, 8, 10), np.uint8), "czyx",
              (1, 0.2, 0.1, 0.1), (None, "micrometer", "micrometer", "micrometer"))
    with pytest.raises(ValueError, match="'c'"):
        read_stack(tmp_path / "c.zarr")


def test_the_napari_reader_opens_a_stack_once_with_its_sampling(tmp_path, monkeypatch):
    import tifffile

    from napari_psfspace._reader import read_tiff

    stack = np.arange(3 * 8 * 9, dtype=np.uint16).reshape(3, 8, 9)
    write_tiff(tmp_path / "z.tif", stack, pixel_size=0.1, z_spacing=0.25)
    opened = []
    real = tifffile.TiffFile.__init__

    def counting(self, *args, **kwargs):
        opened.append(args[0] if args else kwargs)
        real(self, *args, **kwargs)

    monkeypatch.setattr(tifffile.TiffFile, "__init__", counting)
    (data, kwargs, kind), = read_tiff(str(tmp_path / "z.tif"))
    assert len(opened) == 1, opened
    np.testing.assert_array_equal(data, stack)
    assert kind == "image"
    np.testing.assert_allclose(kwargs["scale"], (0.25, 0.1, 0.1))
