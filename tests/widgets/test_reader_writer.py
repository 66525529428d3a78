"""Model reader and writers, TIFF reader, manifest."""

import numpy as np
import pytest

from napari_psfspace import estimate_operator, load_operator
from napari_psfspace._layers import BASIS, OPERATOR_KEY, PSF_GRID, WEIGHT
from napari_psfspace._reader import get_model_reader, get_ome_zarr_reader, get_tiff_reader
from napari_psfspace._writer import write_model, write_psf_tiff
from napari_psfspace.io import read_image, write_tiff


@pytest.fixture(scope="module")
def model(bead_image, tmp_path_factory):
    image, truth = bead_image
    op = estimate_operator(image, psf_radius=truth.psf_radius, holdout=None)
    from napari_psfspace.core.model.operator import ProductConvolution

    op = ProductConvolution(op.basis, op.coefficients, shape=op.image_shape, grid=op.grid,
                            metadata={**op.metadata, "pixel_size_um": 0.065})
    path = tmp_path_factory.mktemp("m") / "model.npz"
    op.save(path)
    return op, path


def test_model_reader_gives_grid_basis_and_scaled_maps(model):
    op, path = model
    reader = get_model_reader(str(path))
    assert reader is not None
    layers = {kw["name"].split(" [")[0]: (d, kw, t) for d, kw, t in reader(str(path))}
    weights = {WEIGHT.format(i + 1) for i in range(op.n_psf)}
    assert set(layers) == {PSF_GRID, BASIS} | weights
    maps, kw, kind = layers[WEIGHT.format(1)]
    # one weight map a layer, covering the image's field in its units (um)
    assert kind == "image" and maps.ndim == 2 and kw["units"] == ("µm", "µm")
    height, width = (n * s for n, s in zip(maps.shape, kw["scale"], strict=True))
    assert height == pytest.approx(op.image_shape[0] * 0.065)
    assert width == pytest.approx(op.image_shape[1] * 0.065)
    assert isinstance(layers[PSF_GRID][1]["metadata"][OPERATOR_KEY], type(op))


def test_model_reader_refuses_other_files(tmp_path):
    other = tmp_path / "other.npz"
    np.savez(other, a=np.arange(3))
    assert get_model_reader(str(other)) is None
    obj = tmp_path / "pickled.npz"
    np.savez(obj, header=np.array([{"format": "x"}], dtype=object))
    assert get_model_reader(str(obj)) is None
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    assert get_model_reader(str(tmp_path / "junk.npz")) is None
    assert get_model_reader(str(tmp_path / "a.tif")) is None


def test_model_writer_round_trip_and_clear_error(model, tmp_path):
    op, path = model
    out = tmp_path / "again.npz"
    assert write_model(str(out), None, {"name": "PSF grid",
                                        "metadata": {OPERATOR_KEY: op}}) == [str(out)]
    assert np.allclose(load_operator(out).basis, op.basis)
    with pytest.raises(ValueError, match="PSF grid"):
        write_model(str(tmp_path / "x.npz"), None, {"name": "img", "metadata": {}})
    assert not (tmp_path / "x.npz").exists()


def test_psf_tiff_writer_keeps_pixel_size(model, tmp_path):
    op, _ = model
    psf = op.psf_at(100.0, 200.0)
    out = tmp_path / "psf.tif"
    write_psf_tiff(str(out), psf, {"metadata": {"pixel_size_um": 0.065, "psf_row": 100.0,
                                                "psf_column": 200.0}})
    data, info = read_image(out)
    # rounded once to float32 in the TIFF
    u32 = np.finfo(np.float32).eps / 2
    assert np.allclose(data, psf, rtol=u32, atol=0) and np.isclose(info.pixel_size, 0.065)


def test_tiff_reader_sets_scale(tmp_path):
    img = tmp_path / "img.tif"
    write_tiff(img, np.ones((20, 30), np.uint16), pixel_size=0.1)
    (data, kw, kind), = get_tiff_reader(str(img))(str(img))
    assert kind == "image" and np.allclose(kw["scale"], (0.1, 0.1))
    stack = tmp_path / "stack.tif"
    write_tiff(stack, np.ones((4, 20, 30), np.float32), pixel_size=0.1)
    (data, kw, kind), = get_tiff_reader(str(stack))(str(stack))
    assert data.shape == (4, 20, 30) and len(kw["scale"]) == 3


def test_ome_zarr_reader_is_lazy_and_sets_the_voxel_size(tmp_path):
    pytest.importorskip("zarr", minversion="3", reason="the OME-Zarr writer takes zarr 3")
    import dask.array as da

    from napari_psfspace.ome_zarr import create_ome_zarr

    arr = create_ome_zarr(tmp_path / "s.zarr", (4, 20, 30), voxel_size=(0.3, 0.1, 0.1))
    arr[2] = 5.0
    (data, kw, kind), = get_ome_zarr_reader(str(tmp_path / "s.zarr"))(str(tmp_path / "s.zarr"))
    assert kind == "image" and isinstance(data, da.Array) and data.shape == (4, 20, 30)
    assert np.allclose(kw["scale"], (0.3, 0.1, 0.1)) and kw["name"] == "s"
    assert float(data[2].mean().compute()) == 5.0
    assert get_ome_zarr_reader(str(tmp_path)) is None  # a folder that is no OME-Zarr


def test_viewer_opens_model_with_plugin(make_napari_viewer, model):
    _, path = model
    v = make_napari_viewer()
    v.open(str(path), plugin="napari-psfspace")
    names = [layer.name for layer in v.layers]
    assert any(n.startswith("PSF grid") for n in names)
    assert any(n.startswith("PSF weight 1") for n in names)
