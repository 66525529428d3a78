"""The paper's Figure 6 experiment on the measured SP8 confocal stack (issue 12).

    python bench/bench_deblur_measured.py [--data ../shared/data] [--offset 3]

The stack (71 slices, 100 nm apart) is the same field at 71 foci. The in-focus slice
``f`` is the sharpest (highest standard deviation); the target is ``f + offset`` (300 nm
from focus by default). A family is learnt from the slices ``f - half .. f + half``
(``half`` 6 by default) without the target, the target's operator is identified from
its own beads (detected) and the target is deblurred (sparse + smooth). Beside it:
Richardson-Lucy (scikit-image, 50 iterations) with the identified operator's PSF at the
field centre.

Figures, on the beads found isolated in the in-focus slice:

- the median FWHM of the beads (pixels; second moments of a background-free 9 x 9
  window, ``2.355 sqrt((m_yy + m_xx) / 2)``) in the in-focus slice, the target, the
  deblurred target and the Richardson-Lucy output;
- the correlation with the in-focus slice of the target, and of the deblurred and
  Richardson-Lucy outputs each seen through one Gaussian of the in-focus beads' width
  (the deblurred beads are points; to compare with the in-focus image they must be seen
  at its resolution);
- the correlation with the in-focus slice of the deblurred and Richardson-Lucy outputs
  *refocused*: seen through the in-focus slice's own operator (``estimate_operator`` on
  that slice alone). A deconvolution that recovered the object predicts the in-focus
  image through the in-focus blur; a Gaussian of the beads' width is a cruder stand-in.

Writes ``docs/measured/sp8_deblur.png``: crops of the in-focus slice, the target, BSS
and Richardson-Lucy. About 2 min.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from skimage.restoration import richardson_lucy

from napari_psfspace.core.beads.detect import detect_beads
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.restore import deblur, identify_operator
from napari_psfspace.io import best_focus_index, read_image, write_png

FILE = "sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif"


def fwhm(image: np.ndarray, centres: np.ndarray, half: int = 4) -> np.ndarray:
    """Second-moment FWHM (pixels) of each spot in a (2 half + 1)^2 window."""
    out = []
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    for y, x in np.round(centres).astype(int):
        win = image[y - half:y + half + 1, x - half:x + half + 1].astype(float)
        if win.shape != yy.shape:
            continue
        ring = np.concatenate([win[0], win[-1], win[:, 0], win[:, -1]])
        w = np.clip(win - np.median(ring), 0, None)
        if w.sum() <= 0:
            continue
        cy, cx = (w * yy).sum() / w.sum(), (w * xx).sum() / w.sum()
        m = ((w * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum() / w.sum()) / 2
        out.append(2.355 * np.sqrt(m))
    return np.array(out)


def corr(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.astype(float).ravel(), b.astype(float).ravel()
    return float(np.corrcoef(a, b)[0, 1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path,
                    default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--offset", type=int, default=3, help="slices from focus (100 nm each)")
    ap.add_argument("--half", type=int, default=6,
                    help="the family learns from slices f - half .. f + half")
    ap.add_argument("--figure", type=Path, default=Path(__file__).resolve().parents[1]
                    / "docs" / "measured" / "sp8_deblur.png")
    args = ap.parse_args()
    path = args.data / FILE
    stack = np.stack([read_image(path, index=z)[0] for z in range(71)])
    pixel = read_image(path, index=0)[1].pixel_size
    f = best_focus_index(stack)
    t = f + args.offset
    train = [z for z in range(f - args.half, f + args.half + 1) if z != t]
    r = 0.5 / pixel
    t0 = time.perf_counter()
    sub = estimate_family([stack[z] for z in train], psf_radius=r, holdout=None)
    t_learn = time.perf_counter() - t0
    target = stack[t].astype(np.float32)
    t0 = time.perf_counter()
    op = identify_operator(target, sub)
    res = deblur(target, op)
    t_bss = time.perf_counter() - t0
    centre = np.clip(op.psf_at((target.shape[0] - 1) / 2, (target.shape[1] - 1) / 2), 0,
                     None)
    rl = richardson_lucy(target, centre, num_iter=50, clip=False)
    focus = stack[f].astype(np.float32)
    beads = detect_beads(stack[f], r)
    pos = beads.positions[beads.kept]
    widths = {name: float(np.median(fwhm(img, pos))) for name, img in (
        ("in focus", focus), ("target", target), ("bss", res.image), ("rl_one", rl))}
    sigma = widths["in focus"] / 2.355
    seen = {name: ndi.gaussian_filter(img, sigma) for name, img in (
        ("bss", res.image), ("rl_one", rl))}
    corrs = {"target": corr(target, focus), "bss": corr(seen["bss"], focus),
             "rl_one": corr(seen["rl_one"], focus)}
    # refocused: each output through the in-focus slice's own operator (learnt from that
    # slice alone, which neither the target's identification nor the deblurring saw)
    op_focus = estimate_operator(stack[f], psf_radius=r, holdout=None)
    refocus = {"target": None,
               "bss": corr(op_focus.apply(res.image), focus),
               "rl_one": corr(op_focus.apply(rl.astype(np.float32)), focus)}
    info = op.metadata["identification"]
    print(f"in-focus slice {f}, target {t} ({100 * args.offset} nm from focus); family "
          f"from slices {train[0]}-{train[-1]} without {t}: I = {sub.n_psf}, J = "
          f"{sub.n_space}, {t_learn:.1f} s; identified from {info['n_beads']} beads, "
          f"deblurred in {res.iterations} iterations ({t_bss:.1f} s)")
    print(f"beads measured: {len(pos)} kept in the in-focus slice")
    print("\n           | median FWHM px | correlation with in-focus | refocused")
    print("------------------------------------------------------------------")
    for name in ("in focus", "target", "bss", "rl_one"):
        c, rc = corrs.get(name), refocus.get(name)
        print(f"{name:>10} | {widths[name]:14.2f} | "
              f"{'-' if c is None else f'{c:.3f}':>25} | "
              f"{'-' if rc is None else f'{rc:.4f}':>9}")
    # figure: a 256 x 256 crop of each, side by side, each scaled to its own range
    cy, cx = (np.array(target.shape) // 2).tolist()
    crop = (slice(cy - 128, cy + 128), slice(cx - 128, cx + 128))
    tiles = [focus[crop], target[crop], res.image[crop], rl[crop]]
    tiles = [(a - np.percentile(a, 1)) / max(np.percentile(a, 99.8) - np.percentile(a, 1),
                                             1e-9) for a in tiles]
    gap = np.ones((256, 6))
    panel = np.concatenate(sum(([np.clip(a, 0, 1), gap] for a in tiles), [])[:-1], axis=1)
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    write_png(args.figure, panel)
    print(f"\nwrote {args.figure}: in focus | {100 * args.offset} nm from focus | BSS | "
          "Richardson-Lucy (one PSF)")


if __name__ == "__main__":
    main()
