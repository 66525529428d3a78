"""The figures the CLI and the demo write: titled, a colour bar in the values' unit, a
scale bar in µm where the pixel size is known."""

from __future__ import annotations

import numpy as np
import pytest

from napari_psfspace.figure import COLORMAPS, NO_DATA, apply_colormap, labelled_figure

INK_LEVEL = 128  # a text pixel is darker than this on the white background


def _ink(region: np.ndarray) -> int:
    return int(np.count_nonzero(region.max(axis=-1) < INK_LEVEL))


def test_the_colour_map_spans_its_anchors_and_marks_missing_values():
    rgb = apply_colormap(np.array([[0.0, 1.0, np.nan, 5.0]]), 0.0, 1.0, "viridis")
    assert tuple(rgb[0, 0]) == COLORMAPS["viridis"][0]
    assert tuple(rgb[0, 1]) == COLORMAPS["viridis"][-1] == tuple(rgb[0, 3])  # clipped
    assert tuple(rgb[0, 2]) == NO_DATA
    with pytest.raises(ValueError, match="cmap"):
        apply_colormap(np.zeros((2, 2)), 0, 1, "jet")


def test_a_figure_has_its_title_bar_and_scale():
    values = np.linspace(0.0, 2.0, 64 * 64).reshape(64, 64)
    plain = labelled_figure(values, title="", unit="", limits=(0.0, 2.0), size=256)
    fig = labelled_figure(values, title="lateral FWHM", unit="µm", limits=(0.0, 2.0),
                          pixel_size=0.1, size=256)
    assert fig.dtype == np.uint8 and fig.ndim == 3
    # the image, enlarged 4x, at (30, 12); the title above it is ink
    assert np.array_equal(fig[30, 12], apply_colormap(np.zeros((1, 1)), 0, 2)[0, 0])
    assert _ink(fig[:28]) > 50 and _ink(plain[:28]) == 0
    # the colour bar right of the image: its top is the map's top colour
    x_bar = 12 + 256 + 12 + 5
    # (inside its outline: one row of a 256-row ramp is 1/255 of the range)
    assert np.abs(fig[31, x_bar].astype(int) - COLORMAPS["viridis"][-1]).max() <= 4
    assert np.abs(fig[30 + 254, x_bar].astype(int) - COLORMAPS["viridis"][0]).max() <= 4
    # the labels beside it and the scale bar under the image (a 6.4 µm field: 1 µm)
    assert _ink(fig[30:290, x_bar + 24:]) > 50
    assert fig.shape[0] > plain.shape[0] and _ink(fig[30 + 256 + 8:30 + 256 + 20, 12:80]) > 100


def test_a_figure_refuses_what_it_cannot_draw():
    with pytest.raises(ValueError, match="2-D"):
        labelled_figure(np.zeros((2, 2, 2)), title="t", unit="")
