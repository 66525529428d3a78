"""The voxel size read from OME-Zarr and OME-TIFF files written by the ecosystem's writers
(``ome-zarr``: ``tests/data/make_ome_zarr_fixtures.py``; ``tifffile``), and checked
against a 3D model's before ``psfspace deblur3d`` does any work."""

import os

import numpy as np
import pytest
import tifffile

from napari_psfspace.cli import main
from napari_psfspace.core.volume.operator3d import ProductConvolution3D
from napari_psfspace.deblur_store import VOXEL_RTOL, stack_voxel_size
from napari_psfspace.io import ImageInfo, read_stack

pytest.importorskip("zarr", minversion="3", reason="the OME-Zarr reader takes zarr 3")

FIXTURES = os.path.join(os.path.dirname(__file__), "data", "ome_zarr")


@pytest.mark.parametrize("name, shape, voxel", [
    ("zyx_v04.zarr", (5, 12, 10), (0.3, 0.1, 0.1)),
    ("zyx_v05.zarr", (5, 12, 10), (0.3, 0.1, 0.1)),
    ("tczyx_nm_v04.zarr", (4, 9, 11), (0.25, 0.065, 0.065)),
])
@pytest.mark.parametrize("lazy", [False, True])
def test_ome_zarr_from_the_ecosystems_writer(name, shape, voxel, lazy):
    data, info = read_stack(os.path.join(FIXTURES, name), lazy=lazy)
    # the full-resolution level, t and c of one dropped, values as written (np.arange)
    assert data.shape == shape
    assert np.array_equal(np.asarray(data), np.arange(np.prod(shape)).reshape(shape))
    assert (info.z_spacing, info.pixel_size) == pytest.approx(voxel[:2], rel=1e-12)


def test_the_napari_reader_scales_an_ome_zarr_from_its_metadata():
    from napari_psfspace._reader import get_ome_zarr_reader

    path = os.path.join(FIXTURES, "tczyx_nm_v04.zarr")
    [(data, kwargs, kind)] = get_ome_zarr_reader(path)(path)
    assert kind == "image" and data.shape == (4, 9, 11) and hasattr(data, "compute")
    assert kwargs["scale"] == pytest.approx((0.25, 0.065, 0.065), rel=1e-12)


def test_ome_tiff_voxel_size(tmp_path):
    stack = np.arange(4 * 6 * 5, dtype=np.uint16).reshape(4, 6, 5)
    tifffile.imwrite(tmp_path / "s.ome.tif", stack, ome=True, metadata={
        "axes": "ZYX", "PhysicalSizeX": 0.065, "PhysicalSizeXUnit": "µm",
        "PhysicalSizeY": 0.065, "PhysicalSizeYUnit": "µm",
        "PhysicalSizeZ": 0.2, "PhysicalSizeZUnit": "µm"})
    for lazy in (False, True):
        data, info = read_stack(tmp_path / "s.ome.tif", lazy=lazy)
        assert np.array_equal(np.asarray(data), stack)
        assert (info.z_spacing, info.pixel_size) == pytest.approx((0.2, 0.065), rel=1e-6)


def _model(voxel, shape=(6, 40, 36)):
    rng = np.random.default_rng(0)
    return ProductConvolution3D(rng.random((2, 3, 5, 5)), rng.random((2, 2, 2)),
                                shape=shape, grid=(np.array([0.0, 39]), np.array([0.0, 35])),
                                plane=1, voxel_size=voxel)


def _info(px, dz):
    return ImageInfo(pixel_size=px, z_spacing=dz, shape=(6, 40, 36), axes="ZYX")


def test_the_stacks_voxel_size_against_the_models():
    model = _model((0.3, 0.1, 0.1))
    assert stack_voxel_size(model, _info(0.1, 0.3)) == (0.3, 0.1, 0.1)
    # within VOXEL_RTOL: the same sampling, metadata rounding
    near = 0.1 * (1 + VOXEL_RTOL / 2)
    assert stack_voxel_size(model, _info(near, 0.3)) == (0.3, near, near)
    with pytest.raises(ValueError, match="no pixel size and no z step.*--pixel-size-nm"):
        stack_voxel_size(model, _info(None, None))
    with pytest.raises(ValueError, match="no z step"):
        stack_voxel_size(model, _info(0.1, None))
    assert stack_voxel_size(model, _info(None, None), voxel_size=(0.3, 0.1, 0.1))
    assert stack_voxel_size(model, _info(0.1, None), voxel_size=(0.3, None, None))
    with pytest.raises(ValueError, match="sampled at 300, 110, 110 nm.*the model at 300, "
                                         "100, 100 nm"):
        stack_voxel_size(model, _info(0.11, 0.3))
    with pytest.raises(ValueError, match="voxel_size"):
        stack_voxel_size(model, _info(0.1, 0.3), voxel_size=(0.3, -1, 0.1))
    # a model in pixels and planes takes any stack, and passes its sampling on
    assert stack_voxel_size(_model(None), _info(None, None)) is None
    assert stack_voxel_size(_model(None), _info(0.1, 0.3)) == (0.3, 0.1, 0.1)


@pytest.mark.parametrize("tiled", [False, True])
def test_deblur3d_refuses_a_stack_of_unknown_sampling_before_any_work(tmp_path, capsys,
                                                                      tiled):
    model = _model((0.3, 0.1, 0.1))
    model.save(tmp_path / "m.npz")
    rng = np.random.default_rng(1)
    stack = rng.poisson(20, model.image_shape).astype(np.uint16)
    tifffile.imwrite(tmp_path / "bare.tif", stack)
    out = tmp_path / ("o.zarr" if tiled else "o.tif")
    extra = ["--tile", "32"] if tiled else []
    cmd = ["deblur3d", str(tmp_path / "bare.tif"), "--model", str(tmp_path / "m.npz"),
           "-o", str(out), "-q", "--iterations", "2", *extra]
    capsys.readouterr()
    assert main(cmd) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--pixel-size-nm" in err and "300, 100, 100" in err
    assert not out.exists() and not os.path.exists(f"{out}.iterates")
    assert main(cmd + ["--pixel-size-nm", "110", "--z-step-nm", "300"]) == 2
    assert "sampled at 300, 110, 110 nm" in capsys.readouterr().err
    assert not out.exists()
    # given: it runs, and the output carries the voxel size given
    assert main(cmd + ["--pixel-size-nm", "100", "--z-step-nm", "300"]) == 0
    _, info = read_stack(out)
    assert (info.z_spacing, info.pixel_size) == pytest.approx((0.3, 0.1), rel=1e-6)
