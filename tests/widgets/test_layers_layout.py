"""The layer package's pieces without a viewer: a new fit starts from the user's beads,
and the colour bars and result slots keep off each other and off the data."""

from __future__ import annotations

import numpy as np


def test_a_new_fit_forgets_the_last_fits_verdicts_only():
    from napari_psfspace._widgets._layers import for_a_new_fit
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


def test_a_colour_bar_lies_right_of_its_map_within_the_column_gap():
    from napari_psfspace._widgets._layers import Frame, beside, map_layers
    from napari_psfspace._widgets._layers.figure import BAR, BAR_TEXT

    frame = Frame((300, 400), (0.1, 0.1), (5.0, -3.0))
    data = np.linspace(0, 1, 300 * 400, dtype=np.float32).reshape(300, 400)
    kwargs = {"name": "thing (µm)", "scale": frame.scale, "translate": frame.translate,
              "colormap": "viridis", "contrast_limits": (0.0, 2.5)}
    (m, mk, _), (bar, bk, _), (pts, pk, kind) = map_layers(data, kwargs, "µm", frame)
    assert bk["name"] == BAR + "thing (µm)" and pk["name"] == BAR_TEXT + "thing (µm)"
    (m_lo, m_hi), (b_lo, b_hi) = _box(m, mk), _box(bar, bk)
    assert np.allclose([b_lo[0], b_hi[0]], [m_lo[0], m_hi[0]])  # as tall as the map
    next_slot = beside(frame, 1.0)[1] - frame.scale[1] / 2
    assert m_hi[1] < b_lo[1] and pts[:, 1].max() < next_slot  # between map and next slot
    assert bar[0, 0] == 2.5 and bar[-1, 0] == 0.0  # top: the upper limit
    assert list(pk["features"]["tick"]) == ["2.5 µm", "1.25 µm", "0 µm"]


def test_a_deblurred_slice_lies_on_its_slice_left_of_the_stack():
    """A 2-D deblur of a stack's slice: one-plane layers on that slice (shown with it
    only), named for it, left of the stack, each with its colour bar."""
    from types import SimpleNamespace

    from napari_psfspace._widgets._deblur import SMOOTH, SPARSE, result_layers
    from napari_psfspace._widgets._layers import Frame

    stack = SimpleNamespace(name="stack", scale=(0.3, 0.1, 0.1), translate=(1.0, 0.0, 0.0))
    res = SimpleNamespace(sparse=np.zeros((20, 30)), smooth=np.ones((20, 30)),
                          parameters={})
    res.sparse[5, 7] = 9.0
    frame = Frame((20, 30), (0.1, 0.1), (0.0, 0.0), index=4)
    out = result_layers(SimpleNamespace(layers=[]), res, frame, stack)
    names = [kw["name"] for _, kw, _ in out]
    assert f"{SPARSE}, slice 4 (image units)" in names
    assert f"{SMOOTH}, slice 4 (image units)" in names
    for data, kw, kind in out:
        z = 1.0 + 4 * 0.3  # the slice's world z
        if kind == "image":
            assert data.shape[0] == 1 and kw["translate"][0] == z and kw["scale"][0] == 0.3
            right = kw["translate"][-1] + data.shape[-1] * kw["scale"][-1]
            assert right < 0.0, kw["name"]  # left of the stack (which starts at x 0)
        else:
            assert np.all(data[:, 0] == z)
    # the sparse part's single point is not lost in the contrast: its limits end at it
    sparse = next(kw for _, kw, _ in out if kw["name"].startswith(SPARSE))
    assert sparse["contrast_limits"] == (0.0, 9.0)
