"""The layer package's pieces without a viewer: a new fit starts from the user's beads,
results lie on the image's field, and maps are marked for napari's overlays."""

from __future__ import annotations

import numpy as np


def test_a_new_fit_forgets_the_last_fits_verdicts_only():
    from napari_psfspace._layers import for_a_new_fit
    from napari_psfspace.core.beads.detect import Beads

    status = np.array(["kept", "heldout", "outlier", "rejected", "saturated"])
    beads = Beads(np.zeros((5, 2)), np.full(5, np.nan), status, np.ones(5))
    got = for_a_new_fit(beads).status.tolist()
    # the held-out split and the outliers were the last fit's; the user's rejection and
    # the detection's flag stay
    assert got == ["kept", "kept", "kept", "rejected", "saturated"]


def _box(data, kwargs):
    scale = np.asarray(kwargs["scale"], float)[-2:]
    lo = np.asarray(kwargs["translate"], float)[-2:] - scale / 2
    return lo, lo + scale * np.asarray(np.shape(data)[-2:])


def test_a_result_lies_centred_on_the_field_at_its_scale():
    """A map on the image's pixels covers the field exactly; a mosaic fills the field
    along its tighter side, centred; a result larger than the field is shrunk to it."""
    from napari_psfspace._layers import Frame, on_field

    frame = Frame((300, 400), (0.1, 0.1), (5.0, -3.0))
    field = (np.array([5.0, -3.0]) - 0.05, np.array([5.0, -3.0]) - 0.05 + [30.0, 40.0])
    same = np.zeros((300, 400))
    lo, hi = _box(same, on_field(frame, same.shape))
    assert np.allclose(lo, field[0]) and np.allclose(hi, field[1])
    mosaic = np.zeros((50, 50))
    kw = on_field(frame, mosaic.shape, fill=1.0)
    lo, hi = _box(mosaic, kw)
    assert np.allclose(hi - lo, [30.0, 30.0])  # as tall as the field, square pixels
    assert np.allclose((lo + hi) / 2, (field[0] + field[1]) / 2)  # centred
    small = on_field(frame, mosaic.shape)  # at the image's scale: not magnified
    assert np.allclose(small["scale"], frame.scale)
    big = np.zeros((600, 200))
    lo, hi = _box(big, on_field(frame, big.shape))
    assert np.all(lo >= field[0] - 1e-9) and np.all(hi <= field[1] + 1e-9)


def test_a_map_is_dressed_by_napari_not_drawn_beside():
    """A map's tuple is one image layer in the image's units, marked for napari's name
    and colour-bar overlays; dress turns them on, and leaves other layers alone."""
    from types import SimpleNamespace

    from napari_psfspace._layers import OVERLAYS_KEY, Frame, dress, map_tuple
    from napari_psfspace._layers.figure import BAR_CORNER, NAME_CORNER

    frame = Frame((30, 40), (0.1, 0.1), units="µm")
    out = map_tuple(np.zeros((30, 40), np.float32),
                    {"name": "thing (µm)", "scale": (0.1, 0.1), "translate": (0, 0),
                     "colormap": "viridis", "contrast_limits": (0.0, 2.5)}, "µm", frame)
    data, kwargs, kind = out
    assert kind == "image" and kwargs["units"] == ("µm", "µm")
    assert kwargs["metadata"][OVERLAYS_KEY] == {"unit": "µm"}

    def overlay():
        return SimpleNamespace(visible=False, position=None, size=None, font_size=None)

    layer = SimpleNamespace(metadata=kwargs["metadata"], colorbar=overlay(),
                            name_overlay=overlay())
    dress(layer)
    assert layer.colorbar.visible and layer.colorbar.position == BAR_CORNER
    assert layer.name_overlay.visible and layer.name_overlay.position == NAME_CORNER
    other = SimpleNamespace(metadata={}, colorbar=overlay(), name_overlay=overlay())
    dress(other)
    assert not other.colorbar.visible and not other.name_overlay.visible


def test_a_deblurred_slice_lies_on_its_slice_on_the_field():
    """A 2-D deblur of a stack's slice: one-plane layers on that slice (shown with it
    only), named for it, on the stack's field."""
    from types import SimpleNamespace

    from napari_psfspace._layers import Frame
    from napari_psfspace._widgets._deblur import SMOOTH, SPARSE, result_layers

    stack = SimpleNamespace(name="stack", scale=(0.3, 0.1, 0.1), translate=(1.0, 0.0, 0.0))
    res = SimpleNamespace(sparse=np.zeros((20, 30)), smooth=np.ones((20, 30)),
                          parameters={})
    res.sparse[5, 7] = 9.0
    frame = Frame((20, 30), (0.1, 0.1), (0.0, 0.0), index=4)
    out = result_layers(res, frame, stack)
    names = [kw["name"] for _, kw, _ in out]
    assert f"{SPARSE}, slice 4 (image units)" in names
    assert f"{SMOOTH}, slice 4 (image units)" in names
    for data, kw, kind in out:
        z = 1.0 + 4 * 0.3  # the slice's world z
        if kind == "image":
            assert data.shape[0] == 1 and kw["translate"][0] == z and kw["scale"][0] == 0.3
            assert np.allclose(kw["translate"][1:], (0.0, 0.0)), kw["name"]  # on the field
            assert np.allclose(kw["scale"][1:], (0.1, 0.1)), kw["name"]
        else:
            assert np.all(data[:, 0] == z)
    # the sparse part's single point is not lost in the contrast: its limits end at it
    sparse = next(kw for _, kw, _ in out if kw["name"].startswith(SPARSE))
    assert sparse["contrast_limits"] == (0.0, 9.0)


def test_colour_limits_span_the_finite_values_and_are_never_empty():
    from napari_psfspace._layers.figure import finite_limits

    assert finite_limits([0.2, np.nan, 0.5]) == (0.2, 0.5)
    lo, hi = finite_limits([3.0, 3.0])  # a constant map: a range above its value
    assert lo == 3.0 and hi > lo
    assert finite_limits([np.nan]) == (0.0, 1.0)
