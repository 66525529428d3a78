"""Tests of the shared input checks (core/_validate.py)."""

import numpy as np
import pytest

from napari_psfspace.core.common.validate import as_image, check_positive, check_psf_radius


def test_3d_stack_suggests_a_slice():
    rng = np.random.default_rng(0)
    stack = np.zeros((5, 16, 16))
    stack[3] = rng.standard_normal((16, 16))  # the only slice with contrast
    with pytest.raises(ValueError, match=r"`image`.*3-D stack.*slice") as info:
        as_image(stack)
    # the hint points at the slice with the highest contrast
    assert "image[3]" in str(info.value)


@pytest.mark.parametrize("shape", [(10,), (2, 3, 4, 5)])
def test_wrong_dimension_mentions_shape(shape):
    with pytest.raises(ValueError, match="`image`") as info:
        as_image(np.zeros(shape))
    assert str(shape) in str(info.value)


def test_custom_name_in_message():
    with pytest.raises(ValueError, match="`beads`"):
        as_image(np.zeros(4), name="beads")


def test_empty_or_thin_image_rejected():
    with pytest.raises(ValueError, match=r"`image`.*\(1, 8\)"):
        as_image(np.zeros((1, 8)))


def test_nan_count_reported():
    img = np.ones((8, 8))
    img[0, 0] = np.nan
    img[3, 4] = np.inf
    img[7, 7] = np.nan
    with pytest.raises(ValueError, match=r"`image` contains 3 NaN or infinite"):
        as_image(img)


def test_complex_rejected():
    with pytest.raises(ValueError, match=r"`image`.*complex"):
        as_image(np.ones((4, 4), dtype=np.complex64))


def test_non_numeric_rejected():
    with pytest.raises(ValueError, match=r"`image`.*numeric"):
        as_image(np.array([["a", "b"], ["c", "d"]]))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.int64, bool,
                                   np.float16, np.float32])
def test_dtype_becomes_float32(dtype):
    src = (np.arange(16).reshape(4, 4) % 2).astype(dtype)
    out = as_image(src)
    assert out.dtype == np.float32
    assert np.array_equal(out, src.astype(np.float32))


def test_float64_kept_and_forced_dtype():
    src = np.linspace(0, 1, 16).reshape(4, 4)
    out = as_image(src)
    assert out.dtype == np.float64
    assert np.array_equal(out, src)
    assert as_image(src.astype(np.uint16), dtype=np.float64).dtype == np.float64


def test_uint16_values_preserved():
    src = np.array([[0, 65535], [1234, 7]], dtype=np.uint16)
    assert as_image(src).tolist() == [[0.0, 65535.0], [1234.0, 7.0]]


def test_check_positive():
    assert check_positive(2, "sigma") == 2.0
    assert check_positive(0, "sigma", allow_zero=True) == 0.0
    for bad in (0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="`sigma`"):
            check_positive(bad, "sigma")
    with pytest.raises(ValueError, match="`sigma` must be a number"):
        check_positive("abc", "sigma")


def test_check_psf_radius():
    assert check_psf_radius(5, (64, 64)) == 5.0
    assert check_psf_radius(1.5, (64, 64)) == 1.5
    with pytest.raises(ValueError, match=r"`psf_radius` must be at least 1.5"):
        check_psf_radius(1.0, (64, 64))
    with pytest.raises(ValueError, match=r"`psf_radius`.*must be finite"):
        check_psf_radius(-3, (64, 64))
    # 2 r + 1 must fit in the smallest side: r = 31.5 fits 64, r = 32 does not
    assert check_psf_radius(31.5, (64, 100)) == 31.5
    with pytest.raises(ValueError, match=r"`psf_radius` = 32 .*too large.*\(64, 100\)"):
        check_psf_radius(32, (64, 100))


def _beads_image():
    import napari_psfspace as ps

    image, _ = ps.simulate_beads((256, 256), n_beads=20, seed=0)
    return image


@pytest.mark.parametrize(("call", "names"), [
    (lambda ps, img: ps.diagnose(img, psf_radius=8, folds=0), "`folds`"),
    (lambda ps, img: ps.estimate_family(np.stack([img] * 3), psf_radius=8, client="x"),
     "`client`"),
    (lambda ps, img: ps.estimate_operator((img > np.percentile(img, 99)).astype(np.uint8),
                                          psf_radius=8), "two values only"),
    (lambda ps, img: ps.estimate_operator(np.full((64, 64), 65535, np.uint16),
                                          psf_radius=8), "constant"),
    (lambda ps, img: ps.simulate_beads((200000, 200000), 10), "GiB"),
    (lambda ps, img: ps.simulate_beads((8, 8), 10), "`shape`"),
    (lambda ps, img: ps.estimate_operator(np.stack([img, img]), psf_radius=8),
     "estimate_operator_3d"),
])
def test_api_doors_name_what_is_wrong(call, names):
    """Calls the issue's fuzz found answered by a numpy-internal error, an
    AttributeError or a model: each now a ValueError naming the argument or the
    reason, before any work (the 200000 x 200000 image is refused before allocating)."""
    import napari_psfspace as ps

    with pytest.raises(ValueError, match=names) as info:
        call(ps, _beads_image())
    assert "has not landed" not in str(info.value)


def test_a_psf_outside_the_field_is_refused_as_on_the_command_line():
    import napari_psfspace as ps
    from napari_psfspace.core.simulation.optics import simulate_psf

    op = ps.estimate_operator(_beads_image(), psf_radius=8)
    h, w = op.image_shape
    assert op.psf_at(h - 1, 0).shape[0] == op.psf_size  # the field's corner is in it
    for y, x in ((1e9, 1e9), (-1, 0), (0, w - 0.5), (np.nan, 0)):
        with pytest.raises(ValueError, match=r"`y`, `x`.*outside the model's field"):
            op.psf_at(y, x)
    with pytest.raises(ValueError, match="`shift`"):
        simulate_psf(None, shift=(np.nan, 0))
