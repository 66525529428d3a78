"""Figures a person reads without the code beside them: a title, the image in a stated
colour map, a colour bar whose labels give its limits in the values' unit, and a scale
bar in µm where the pixel size is known. Written as PNG by the CLI's reports and the
demo (Pillow draws the texts; it comes with scikit-image).

The figure is an RGB array (:func:`labelled_figure`) so that it is tested like any
other; :func:`write_figure` writes it atomically.
"""

from __future__ import annotations

import os

import numpy as np

#: Anchor colours (RGB, 0-255) of the colour maps, interpolated linearly: viridis and
#: magma sampled at equal steps of their published tables; "diverging" blue-white-red;
#: "grey" black to white.
COLORMAPS = {
    "viridis": [(68, 1, 84), (72, 40, 120), (62, 74, 137), (49, 104, 142), (38, 130, 142),
                (31, 158, 137), (53, 183, 121), (109, 205, 89), (180, 222, 44),
                (253, 231, 37)],
    "magma": [(0, 0, 4), (28, 16, 68), (79, 18, 123), (129, 37, 129), (181, 54, 122),
              (229, 80, 100), (251, 135, 97), (254, 194, 135), (252, 253, 191)],
    "diverging": [(33, 102, 172), (103, 169, 207), (209, 229, 240), (247, 247, 247),
                  (253, 219, 199), (239, 138, 98), (178, 24, 43)],
    "grey": [(0, 0, 0), (255, 255, 255)],
}
#: Colour of a pixel without a value (NaN).
NO_DATA = (48, 48, 48)
BACKGROUND = (255, 255, 255)
INK = (20, 20, 20)


def apply_colormap(values: np.ndarray, vmin: float, vmax: float,
                   cmap: str = "viridis") -> np.ndarray:
    """RGB image (M, N, 3) uint8 of a 2-D array: ``vmin`` .. ``vmax`` over the colour
    map's anchors (clipped), NaN in :data:`NO_DATA`."""
    if cmap not in COLORMAPS:
        raise ValueError(f"`cmap` must be one of {sorted(COLORMAPS)}, got {cmap!r}")
    lut = np.asarray(COLORMAPS[cmap], float)
    v = np.asarray(values, float)
    t = np.clip((v - vmin) / (vmax - vmin if vmax > vmin else 1.0), 0.0, 1.0)
    t = np.nan_to_num(t) * (len(lut) - 1)
    i = np.minimum(t.astype(int), len(lut) - 2)
    f = (t - i)[..., None]
    rgb = (1 - f) * lut[i] + f * lut[i + 1]
    rgb[~np.isfinite(v)] = NO_DATA
    return np.round(rgb).astype(np.uint8)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: one bitmap size
        return ImageFont.load_default()


def _plain(text: str) -> str:
    """Pillow's default font has no micro sign: "um" where the text says µm."""
    return text.replace("µ", "u").replace("μ", "u")


def _tick(value: float, unit: str) -> str:
    text = f"{value:.0f}" if 1e4 <= abs(value) < 1e7 else f"{value:.3g}"
    return f"{text} {unit}" if unit and len(unit) <= 4 else text


def _scale_bar_length(field_um: float) -> float:
    """A round length (1, 2 or 5 x 10^k µm) about a fifth of the field."""
    target = field_um / 5
    exp = np.floor(np.log10(target))
    for m in (5, 2, 1):
        if m * 10 ** exp <= target:
            return float(m * 10 ** exp)
    return float(10 ** exp)


def labelled_figure(values: np.ndarray, *, title: str, unit: str,
                    limits: tuple[float, float] | None = None, cmap: str = "viridis",
                    pixel_size: float | None = None, size: int = 512,
                    note: str = "") -> np.ndarray:
    """A titled figure of a 2-D array with its colour bar and, when the pixel size is
    known, a scale bar.

    Parameters
    ----------
    values : ndarray of shape (M, N)
        The quantity (NaN: no value).
    title : str
        One line above the image.
    unit : str
        Unit of the values, named above the colour bar ("relative" for tiles scaled to
        their largest magnitude); a short unit (µm, nm, px) is also written after each
        limit. µ is written "u" (the default font has no micro sign).
    limits : (float, float), optional
        The colour bar's bottom and top; default the finite range of ``values``.
    cmap : str
        A key of :data:`COLORMAPS`.
    pixel_size : float, optional
        µm per pixel of ``values``: a scale bar of a round length is drawn under it.
    size : int
        The longer side of the image in the figure, pixels (pixels are repeated).
    note : str
        An optional line under the image (what a tile is, how it was scaled).

    Returns
    -------
    ndarray of shape (H, W, 3), uint8
    """
    from PIL import Image, ImageDraw

    v = np.asarray(values, float)
    if v.ndim != 2 or v.size == 0:
        raise ValueError(f"`values` must be a non-empty 2-D array, got shape {v.shape}")
    finite = v[np.isfinite(v)]
    if limits is None:
        limits = ((float(finite.min()), float(finite.max())) if finite.size
                  else (0.0, 1.0))
    lo, hi = (float(x) for x in limits)
    k = max(1, int(round(size / max(v.shape))))
    img = np.repeat(np.repeat(apply_colormap(v, lo, hi, cmap), k, axis=0), k, axis=1)
    h, w = img.shape[:2]
    pad, title_h, bar_w, label_w = 12, 30, 18, 90
    below = 30 * (bool(pixel_size) + bool(note))
    canvas = Image.new("RGB", (pad + w + pad + bar_w + 6 + label_w + pad,
                               title_h + h + below + pad), BACKGROUND)
    canvas.paste(Image.fromarray(img), (pad, title_h))
    draw = ImageDraw.Draw(canvas)
    big, small = _font(16), _font(12)
    title, unit, note = _plain(title), _plain(unit), _plain(note)
    draw.text((pad, 6), title, fill=INK, font=big)
    # the colour bar: top = hi
    ramp = np.linspace(hi, lo, h)[:, None] * np.ones((1, bar_w))
    x_bar = pad + w + pad
    canvas.paste(Image.fromarray(apply_colormap(ramp, lo, hi, cmap)), (x_bar, title_h))
    draw.rectangle((x_bar, title_h, x_bar + bar_w - 1, title_h + h - 1), outline=INK)
    x_lab = x_bar + bar_w + 6
    draw.text((x_bar, title_h - 16), unit, fill=INK, font=small)
    for y, value in ((title_h, hi), (title_h + h // 2 - 6, (lo + hi) / 2),
                     (title_h + h - 13, lo)):
        draw.text((x_lab, y), _tick(value, unit), fill=INK, font=small)
    y = title_h + h + 8
    if pixel_size:
        um_per_px = float(pixel_size) / k
        length = _scale_bar_length(v.shape[1] * float(pixel_size))
        bar = int(round(length / um_per_px))
        draw.rectangle((pad, y + 4, pad + bar, y + 9), fill=INK)
        draw.text((pad + bar + 8, y), f"{length:g} um", fill=INK, font=small)
        y += 30
    if note:
        draw.text((pad, y), note, fill=INK, font=small)
    return np.asarray(canvas)


def figure_png(values: np.ndarray, **kwargs) -> bytes:
    """:func:`labelled_figure` as the bytes of a PNG file."""
    from .io import png_bytes

    return png_bytes(labelled_figure(values, **kwargs))


def write_figure(path: str | os.PathLike, values: np.ndarray, **kwargs) -> None:
    """:func:`labelled_figure` written as a PNG, atomically."""
    from .io import write_png

    write_png(path, labelled_figure(values, **kwargs))


__all__ = ["COLORMAPS", "apply_colormap", "labelled_figure", "write_figure"]
