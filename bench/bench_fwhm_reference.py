"""The FWHM a microscopist reads, against tools and truths the project did not write.

For each bead z-stack the project's widths are set beside an outside reference:

* **measured** (``../shared/data``): every z-stack there. The project's 3D estimate
  (``estimate_operator_3d``, the CLI's defaults but the PSF radius) gives the beads; at
  each bead the table has the model's PSF (map), the bead's own pixels (per bead:
  ``direct_bead_measures``, not re-sampled nor moved in z) and
  **napari-psf-analysis** 1.2 run on the same bead (its bead extractor, its Gaussian
  fits: 2-D on the plane of the bead's peak, 1-D along the axis through it; box 2 µm x
  6 µm as its panel's defaults, 4 µm deep where the stack is shallower). Single-bead
  stacks have no field: the project's measure of the bead against napari-psf-analysis'.
  Without a pixel size in the file, lengths are in pixels and planes for both.
* **pyotf** and **psfmodels** (code the project did not write): a field of beads, one
  PSF for all (so that the truth is one number), each bead at its own depth within
  +-0.5 µm (``--z-spread``), noise as a camera gives it; napari-psf-analysis runs on
  the same beads too. The truth
  is the optical PSF's own half-maximum width on a grid 5x finer than the pixels
  (laterally along rows and columns through the peak; axially along the optical axis on
  planes 5x finer), no Gaussian in it.

* ``--sets pyotf-widefield psfmodels-widefield``: the same at the sampling of a
  widefield stack (NA 0.95, 108 nm pixels, 300 nm planes, 31 planes);
  ``pyotf-highna psfmodels-highna``: at that of two public high-NA stacks (NA 1.46,
  160 nm pixels, 200 nm planes, 31 planes).
* **astigmatism** (``--sets astigmatism``): pyotf PSFs with vertical astigmatism (Noll 6,
  0-0.2 waves rms) at NA 0.85 and 1.3, 12 noisy pixel-integrated beads each; the truth
  is the split between the line foci of the noise-free PSF on planes 5x finer, its
  widths from scipy's ``curve_fit`` (an axis-aligned Gaussian with an offset, +-1 µm
  about the peak), each line focus the width minimum nearest the plane of the highest
  peak. Bound: 0.1 µm (one 100 nm plane).

Ratios: project / reference. Bounds (issue 44): measured lateral within 10 %, axial
within 15 % of napari-psf-analysis; simulated within 5 % of the truth.

    pip install -e ".[bench]"    # napari-psf-analysis, pyotf, psfmodels
    python bench/bench_fwhm_reference.py [--sets measured pyotf psfmodels astigmatism]
                                         [--seed 0]
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from benchlib import table
from napari_psfspace.core.common.measures import psf_measures
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.volume import iter_estimate_operator_3d
from napari_psfspace.core.volume.measures import direct_bead_measures, model_measures

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
#: (path under ../shared/data, PSF radius in px); the voxel size is the file's.
MEASURED = (
    ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", 22),
    ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", 16),
    ("single_bead_psfs/Bead_Image1_crop.tif", 16),
    ("single_bead_psfs/BIL113_zstack_z300nm_current.tif", 16),
    ("single_bead_psfs/pycudadecon_psf.tif", 16),
)


def reference_fwhm(stack: np.ndarray, points: np.ndarray, spacing, box=(6.0, 2.0, 2.0)
                   ) -> list[dict | None]:
    """napari-psf-analysis on the beads at ``points`` (z, y, x in voxels): its bead
    extractor and its fits; FWHM in the units of ``spacing`` (None: a bead it discarded
    or could not fit)."""
    from napari_psf_analysis.psf_analysis.extract.BeadExtractor import BeadExtractor
    from napari_psf_analysis.psf_analysis.image import Calibrated3DImage
    from napari_psf_analysis.psf_analysis.psf import PSF

    depth = stack.shape[0] * spacing[0]
    box = (min(box[0], 0.66 * depth), box[1], box[2])
    # their fits record the background as non-negative: a background-subtracted PSF is
    # lifted by a constant (no width changes with it)
    stack = stack - min(float(stack.min()), 0.0) + 1.0
    out = []
    for p in points:
        ext = BeadExtractor(image=Calibrated3DImage(data=stack, spacing=tuple(spacing)),
                            patch_size=box)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                beads = ext.extract_beads(points=np.asarray([p]))
                if not beads:
                    out.append(None)
                    continue
                psf = PSF(image=beads[0])
                psf.analyze()
                r = psf.get_summary_dict()
        except Exception as exc:  # their fit failing on a bead is a row, not a stop
            print(f"  napari-psf-analysis failed at {np.round(p, 1)}: {exc}")
            out.append(None)
            continue
        out.append({"row": r["y_fwhm"], "col": r["x_fwhm"], "axial": r["z_fwhm"],
                    "pa1": r["yx_pc1_fwhm"], "pa2": r["yx_pc2_fwhm"]})
    return out


def _ratio_row(name, n, ours: dict, ref: dict, what: str) -> dict:
    row = {"stack": name, "what": what, "n": n}
    for k in ("row", "col", "lateral", "axial"):
        row[f"{k}"] = float(np.nanmedian(ours[k]))
        row[f"{k}_ref"] = float(np.nanmedian(ref[k]))
        row[f"{k}_x"] = float(np.nanmedian(np.asarray(ours[k]) / np.asarray(ref[k])))
    return row


def _phys(m: dict, vox) -> dict:
    """The widths in the units of ``vox`` (dz, dy, dx)."""
    return {"row": m["fwhm_row"] * vox[1], "col": m["fwhm_col"] * vox[2],
            "lateral": m["fwhm_lateral"] * vox[1], "axial": m["fwhm_axial"] * vox[0]}


def measured() -> list[dict]:
    from napari_psfspace.io import read_stack

    rows = []
    for rel, radius in MEASURED:
        path = DATA / rel
        if not path.exists():
            print(f"skipped {rel}: ../shared/data is not beside the repository")
            continue
        stack, info = read_stack(path)
        if info.pixel_size and info.z_spacing:
            vox, unit = (info.z_spacing, info.pixel_size, info.pixel_size), "um"
        else:
            vox, unit = (1.0, 1.0, 1.0), "px"
        # napari-psf-analysis' default box (2 µm wide, 6 µm deep) in pixels where the
        # file gives no size: 21 px (2 µm at 0.1 µm pixels) and two thirds of the planes
        box = (6.0, 2.0, 2.0) if unit == "um" else (stack.shape[0], 21, 21)
        name = f"{path.stem[:22]} ({unit})"
        t0 = time.perf_counter()
        try:
            est = run_with_progress(iter_estimate_operator_3d(stack, psf_radius=radius))
        except ValueError as exc:
            est = None
            print(f"{rel}: no 3D model ({exc}); the bead alone")
        if est is not None:
            inl = est.basis.inliers
            centers = est.patches.centers[inl]
            beads = direct_bead_measures(stack, est)  # each bead on its own pixels
            model = model_measures(est.operator, centers)
            planes = beads["focal_plane"]
        else:  # one bead: its brightest voxel, a patch about it
            from scipy import ndimage as ndi

            sm = ndi.gaussian_filter(stack.astype(float), 2)
            z, y, x = np.unravel_index(int(np.argmax(sm)), sm.shape)
            centers = np.array([[y, x]], float)
            r = radius
            patch = stack[:, max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1].astype(float)
            patch -= np.median(stack)
            m = psf_measures(patch)
            beads = {k: np.array([v]) for k, v in m.items()}
            model = None
            planes = beads["focal_plane"]
        points = np.column_stack([planes, centers])
        ref = reference_fwhm(stack.astype(np.float64), points, vox, box)
        ok = np.array([r is not None for r in ref])
        refd = {k: np.array([r[k] if r else np.nan for r in ref]) for k in
                ("row", "col", "axial")}
        refd["lateral"] = np.sqrt(refd["row"] * refd["col"])

        rows.append(_ratio_row(name, int(ok.sum()), _phys(beads, vox), refd, "per bead"))
        if model is not None:
            rows.append(_ratio_row(name, int(ok.sum()), _phys(model, vox), refd,
                                   "map at beads"))
        print(f"{rel}: {len(points)} beads, {int(ok.sum())} measured by napari-psf-analysis, "
              f"{time.perf_counter() - t0:.1f} s")
        if model is not None:  # the split (napari-psf-analysis has none): beads, map
            from napari_psfspace.core.volume.measures import measure_maps

            grid = measure_maps(est.operator)[2]["astigmatic_split"]
            b, m = beads["astigmatic_split"], model["astigmatic_split"]
            def q(a):
                return "median {:+.2f} (10-90 %: {:+.2f} to {:+.2f})".format(
                    *np.nanpercentile(a, [50, 10, 90]))
            print(f"  astigmatic split (planes of {vox[0]:g} {unit}): per bead {q(b)}; "
                  f"map at the beads {q(m)}; 8 x 8 map {np.nanmin(grid):+.2f} to "
                  f"{np.nanmax(grid):+.2f}, |split| >= 2 at {int(np.sum(np.abs(grid) >= 2))}"
                  f" of {np.isfinite(grid).sum()} nodes")
    return rows


def _half_width(profile: np.ndarray, step: float) -> float:
    """Half-maximum width of a sampled profile (linear between samples)."""
    k = int(np.argmax(profile))
    half = profile[k] / 2
    left = np.flatnonzero(profile[:k] < half)
    right = np.flatnonzero(profile[k:] < half)
    if not len(left) or not len(right):
        return np.nan
    i, j = left[-1], k + right[0]
    zl = i + (half - profile[i]) / (profile[i + 1] - profile[i])
    zr = j - 1 + (profile[j - 1] - half) / (profile[j - 1] - profile[j])
    return float((zr - zl) * step)


def simulated_psf(generator: str, na: float, wl: float, dxy: float, dz: float, nz: int,
                  q: int = 5, size: int = 33, mismatch: bool = False):
    """A stack PSF sampled ``q`` times finer than the pixels and planes, and the true
    FWHM (µm). ``mismatch``: a refractive-index mismatch (pyotf: 0.15 waves rms of
    primary spherical aberration; psfmodels: an oil objective focused 3 µm into water)."""
    n = q * size
    zf = (np.arange(q * (nz - 1) + 1) - q * (nz - 1) / 2) * dz / q  # µm, fine planes
    if generator == "pyotf":
        from pyotf.otf import HanserPSF

        ni = 1.52 if na > 1.33 else 1.33
        model = HanserPSF(wl=wl * 1000, na=na, ni=ni, res=dxy * 1000 / q, size=n,
                          zrange=list(zf * 1000), vec_corr="total", condition="sine")
        if mismatch:
            from pyotf.otf import apply_aberration

            pcoefs = np.zeros(11)
            pcoefs[10] = 2 * np.pi * 0.15  # Noll 11, radians rms
            model = apply_aberration(model, None, pcoefs)
        fine = np.asarray(model.PSFi, float)
    else:
        import psfmodels as pm

        fine = pm.vectorial_psf(zf + (3.0 if mismatch else 0.0), nx=n + 1, dxy=dxy / q,
                                pz=3.0 if mismatch else 0.0, wvl=wl,
                                params={"NA": na, "ni": 1.515, "ni0": 1.515,
                                        "ns": 1.33 if mismatch else 1.515})
        fine = np.asarray(fine, float)[:, :n, :n]
    kz, ky, kx = np.unravel_index(int(np.argmax(fine)), fine.shape)
    true = {"row": _half_width(fine[kz, :, kx], dxy / q),
            "col": _half_width(fine[kz, ky, :], dxy / q),
            "axial": _half_width(fine[:, ky, kx], dz / q)}
    true["lateral"] = float(np.sqrt(true["row"] * true["col"]))
    return fine, (kz, ky, kx), true


def simulated(generator: str, seed: int, na: float, wl=0.6, dxy=0.065, nz=41,
              photons=20000.0, dz: float | None = None, z_spread: float = 0.5,
              pixel_truth: bool = False) -> list[dict]:
    """A field of beads with one PSF, pixel-integrated from fifths of a pixel (each bead
    on one of the ``q x q`` sub-pixel phases), Poisson noise over a background; planes a
    tenth of the diffraction-limited axial FWHM apart (the stack spans +- 2 FWHM). Each
    bead lies at its own depth, uniform over ``+-z_spread`` µm (on the fine planes, a
    fifth of a plane apart), so that the estimate must register them in z.

    Rows: the project (per bead, and its model at the beads) against the truth, and
    against napari-psf-analysis on the same beads; and napari-psf-analysis against the
    truth (how far the reference itself is). ``pixel_truth``: also against the
    half-maximum width of the PSF integrated over one camera pixel (the in-focus plane
    convolved with a pixel-sized box on the fine grid), what a perfect fit to pixels
    could read."""
    from napari_psfspace.core.common.measures import diffraction_limit

    q, size = 5, 33
    ni = 1.52 if generator == "pyotf" and na > 1.33 else (
        1.33 if generator == "pyotf" else 1.515)
    if dz is None:
        dz = round(diffraction_limit(na, wl, refractive_index=ni)["axial"] / 10, 3)
    margin = int(np.ceil(z_spread / dz)) + 1  # planes beyond the stack on each side
    fine, (kz, ky, kx), true = simulated_psf(generator, na, wl, dxy, dz, nz + 2 * margin,
                                             q, size)
    rng = np.random.default_rng(seed)
    shape = (nz, 256, 256)
    clean = np.full(shape, 20.0)
    half = size // 2
    pos, depth = [], []
    reach = int(np.floor(z_spread / (dz / q)))
    for y in range(28, 230, 40):
        for x in range(28, 230, 40):
            py, px = rng.integers(0, q, 2)
            shift = int(rng.integers(-reach, reach + 1))  # fine planes: the bead's depth
            # stack plane j sees the fine plane q (margin + j) - shift
            planes = fine[q * margin - shift::q][:nz]
            sl = np.roll(planes, (py - q // 2, px - q // 2), axis=(1, 2))
            binned = sl.reshape(len(sl), size, q, size, q).sum(axis=(2, 4))
            zpad = np.zeros((nz, size, size))
            zpad[:len(binned)] = binned
            clean[:, y - half:y + half + 1, x - half:x + half + 1] += (
                photons * zpad / binned.sum(axis=(1, 2)).max())
            pos.append((y, x))
            depth.append(shift * dz / q)
    stack = rng.poisson(clean).astype(np.float32)
    est = run_with_progress(iter_estimate_operator_3d(stack, psf_radius=12))
    inl = est.basis.inliers
    beads = direct_bead_measures(stack, est)  # each bead on its own pixels
    centers = est.patches.centers[inl]
    model = model_measures(est.operator, centers)
    vox = (dz, dxy, dxy)
    # napari-psf-analysis on the same beads, each at its own focus
    points = np.column_stack([np.round(est.bead_focus[inl]), centers])
    ref = reference_fwhm(stack.astype(np.float64), points, vox)  # its fit takes the offset
    refd = {k: np.array([r[k] if r else np.nan for r in ref]) for k in ("row", "col", "axial")}
    refd["lateral"] = np.sqrt(refd["row"] * refd["col"])
    # the beads' depths as the estimate found them, against the planted ones
    near = [int(np.argmin(np.hypot(*(np.asarray(pos) - c).T))) for c in centers]
    planted = np.asarray(depth)[near]
    found = (est.bead_focus[inl] - (nz - 1) / 2) * dz
    off = found - planted - np.nanmedian(found - planted)  # one common offset allowed
    surface = est.operator.metadata["focal_surface"]

    # no astigmatism in these PSFs: the split map should read 0 everywhere
    from napari_psfspace.core.volume.measures import measure_maps

    grid = measure_maps(est.operator, 9, 9)[2]["astigmatic_split"]
    bs = beads["astigmatic_split"]
    print(f"{generator} NA {na} (planes of {dz:g} um, beads +-{z_spread:g} um in z): "
          f"bead depths found within {np.sqrt(np.nanmean(off ** 2)) * 1000:.0f} nm rms; "
          f"{surface['n_off']} bead(s) left out off the focal surface; split per bead "
          f"median {np.nanmedian(bs):+.2f}, |.| max {np.nanmax(np.abs(bs)):.2f}; 9 x 9 map "
          f"{np.nanmin(grid):+.2f} to {np.nanmax(grid):+.2f}, |split| >= 2 at "
          f"{int(np.sum(np.abs(grid) >= 2))} of {int(np.isfinite(grid).sum())} nodes",
          flush=True)
    k = int(inl.sum())
    truth = {key: np.full(k, v) for key, v in true.items()}
    name = f"{generator} NA {na} s{seed} (um)"
    n_ref = int(np.isfinite(refd["axial"]).sum())
    rows = [_ratio_row(name, k, _phys(beads, vox), truth, "per bead / truth"),
            _ratio_row(name, k, _phys(model, vox), truth, "map at beads / truth"),
            _ratio_row(name, n_ref, _phys(beads, vox), refd, "per bead / n-p-a"),
            _ratio_row(name, n_ref, _phys(model, vox), refd, "map at beads / n-p-a"),
            _ratio_row(name, n_ref, refd, truth, "n-p-a / truth")]
    if pixel_truth:
        from scipy import ndimage as ndi

        box = ndi.uniform_filter(fine[kz], size=q, mode="constant")
        by, bx = np.unravel_index(int(np.argmax(box)), box.shape)
        pix = {"row": _half_width(box[:, bx], dxy / q), "col": _half_width(box[by, :], dxy / q),
               "axial": true["axial"]}
        pix["lateral"] = float(np.sqrt(pix["row"] * pix["col"]))
        print(f"{generator} NA {na}: the optical PSF's lateral FWHM {true['lateral']:.3f} um, "
              f"integrated over a pixel {pix['lateral']:.3f} um", flush=True)
        # what re-sampling does to a spot this narrow: the in-focus plane binned to pixels
        # on a pixel's centre, moved by a fraction of a pixel (cubic spline, Fourier),
        # widths from scipy's curve_fit
        binned = fine[kz].reshape(size, q, size, q).sum(axis=(1, 3))
        for d in (0.2, 0.4):
            cub = ndi.shift(binned, (d, d), order=3, mode="constant")
            fou = np.fft.ifftn(ndi.fourier_shift(np.fft.fftn(binned), (d, d))).real
            w0, w3, wf = (np.sqrt(np.prod(_gauss_widths(a, dxy))) for a in (binned, cub, fou))
            print(f"  re-sampled by {d:.1f} px: Gaussian FWHM {w0:.3f} um on the pixels, "
                  f"{w3:.3f} after a cubic spline, {wf:.3f} after a Fourier shift", flush=True)
        ptruth = {key: np.full(k, v) for key, v in pix.items()}
        rows += [_ratio_row(name, k, _phys(beads, vox), ptruth, "per bead / pixel truth"),
                 _ratio_row(name, k, _phys(model, vox), ptruth, "map / pixel truth"),
                 _ratio_row(name, n_ref, refd, {kk: v[:n_ref] for kk, v in ptruth.items()},
                            "n-p-a / pixel truth")]
    return rows


def _gauss_widths(plane: np.ndarray, step: float) -> tuple[float, float]:
    """Row and column FWHM (units of ``step``) of an axis-aligned Gaussian with an
    offset, fitted by scipy's ``curve_fit`` (not the project's fitter)."""
    from scipy.optimize import curve_fit

    yy, xx = np.indices(plane.shape) * step

    def g(yx, a, y0, x0, sy, sx, b):
        return a * np.exp(-(yx[0] - y0) ** 2 / (2 * sy ** 2)
                          - (yx[1] - x0) ** 2 / (2 * sx ** 2)) + b

    ky, kx = np.unravel_index(int(np.argmax(plane)), plane.shape)
    try:
        p, _ = curve_fit(g, (yy.ravel(), xx.ravel()), plane.ravel(),
                         p0=[plane.max(), ky * step, kx * step, 0.15, 0.15, 0.0], maxfev=4000)
    except RuntimeError:
        return np.nan, np.nan
    return abs(p[3]) * 2.3548, abs(p[4]) * 2.3548


def _nearest_minimum(z: np.ndarray, w: np.ndarray, k0: int) -> float:
    """Descend from index ``k0`` to the nearest minimum of ``w``; parabola vertex."""
    k = k0
    while True:
        nb = [j for j in (k - 1, k + 1) if 0 <= j < len(w) and np.isfinite(w[j]) and w[j] < w[k]]
        if not nb:
            break
        k = min(nb, key=lambda j: w[j])
    if 0 < k < len(w) - 1 and np.all(np.isfinite(w[k - 1:k + 2])):
        a, b, c = w[k - 1:k + 2]
        den = a - 2 * b + c
        return float(z[k] + (0.5 * (a - c) / den if den else 0.0) * (z[1] - z[0]))
    return float(z[k])


def astigmatism(seed: int, nas=(0.85, 1.3), amounts=(0.0, 0.05, 0.1, 0.15, 0.2),
                wl=0.52, dxy=0.0635, dz=0.1, nz=41, photons=20000.0, n=12) -> list[dict]:
    """The split of pyotf's astigmatic PSFs: the project's per-bead measure on noisy
    pixel-integrated beads against the noise-free PSF's line foci (µm)."""
    from pyotf.otf import HanserPSF, apply_aberration

    q, size = 5, 33
    rng = np.random.default_rng(seed)
    rows = []
    for na in nas:
        for amount in amounts:
            zf = (np.arange(q * (nz - 1) + 1) - q * (nz - 1) / 2) * dz / q
            model = HanserPSF(wl=wl * 1000, na=na, ni=1.52 if na > 1.33 else 1.33,
                              res=dxy * 1000 / q, size=q * size, zrange=list(zf * 1000),
                              vec_corr="total", condition="sine")
            pc = np.zeros(6)
            pc[5] = 2 * np.pi * amount  # Noll 6 (vertical astigmatism), radians rms
            fine = np.asarray(apply_aberration(model, None, pc).PSFi, float)
            peaks = fine.max(axis=(1, 2))
            c, h = fine.shape[1] // 2, int(round(1.0 / (dxy / q)))
            wr, wc = np.full(len(zf), np.nan), np.full(len(zf), np.nan)
            for i in np.flatnonzero(peaks >= 0.3 * peaks.max()):
                wr[i], wc[i] = _gauss_widths(fine[i, c - h:c + h + 1, c - h:c + h + 1],
                                             dxy / q)
            k0 = int(np.argmax(peaks))
            true = _nearest_minimum(zf, wc, k0) - _nearest_minimum(zf, wr, k0)
            got = []
            for _ in range(n):
                py, px, pz = rng.integers(0, q, 3)
                planes = np.roll(fine[pz::q][:nz], (py - q // 2, px - q // 2), axis=(1, 2))
                binned = planes.reshape(len(planes), size, q, size, q).sum(axis=(2, 4))
                vol = np.zeros((nz, size, size))
                vol[:len(binned)] = binned
                clean = 20.0 + photons * vol / binned.sum(axis=(1, 2)).max()
                got.append(psf_measures(rng.poisson(clean) - 20.0)["astigmatic_split"] * dz)
            got = np.array(got)
            rows.append({"na": na, "waves_rms": amount, "true_um": true,
                         "median_um": float(np.nanmedian(got)),
                         "p10_um": float(np.nanpercentile(got, 10)),
                         "p90_um": float(np.nanpercentile(got, 90)),
                         "off_um": float(np.nanmedian(got) - true),
                         "nan": int(np.isnan(got).sum())})
            print(f"astigmatism NA {na} {amount} waves: true {true:+.3f} um, "
                  f"median {rows[-1]['median_um']:+.3f} um", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", nargs="+", default=["measured", "pyotf", "psfmodels"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--na", type=float, nargs="+", default=[0.8, 1.3, 1.45])
    ap.add_argument("--z-spread", type=float, default=0.5,
                    help="simulated beads lie uniformly within +- this depth, µm")
    args = ap.parse_args()
    if "astigmatism" in args.sets:
        arows = astigmatism(args.seed)
        print("\nAstigmatic split (µm, z_col - z_row): per-bead measure on 12 noisy beads "
              "against the noise-free pyotf PSF's line foci")
        print(table(arows, [("na", ".2f"), ("waves_rms", ".2f"), ("true_um", "+.3f"),
                            ("median_um", "+.3f"), ("p10_um", "+.3f"), ("p90_um", "+.3f"),
                            ("off_um", "+.3f"), ("nan", "d")]))
        if args.sets == ["astigmatism"]:
            return
    rows = []
    if "measured" in args.sets:
        rows += measured()
    for gen in ("pyotf", "psfmodels"):
        if gen in args.sets:
            for na in args.na:
                rows += simulated(gen, args.seed, na, z_spread=args.z_spread)
        if f"{gen}-widefield" in args.sets:  # the issue's widefield stack's sampling
            rows += simulated(gen, args.seed, 0.95, wl=0.52, dxy=0.108, nz=31, dz=0.3,
                              z_spread=args.z_spread)
        if f"{gen}-highna" in args.sets:  # the sampling of the two high-NA stacks
            rows += simulated(gen, args.seed, 1.46, wl=0.6, dxy=0.16, nz=31, dz=0.2,
                              z_spread=args.z_spread, pixel_truth=True)
    cols = [("stack", "s"), ("what", "s"), ("n", "d")]
    for k in ("row", "col", "lateral", "axial"):
        cols += [(k, ".3f"), (f"{k}_ref", ".3f"), (f"{k}_x", ".3f")]
    print("\nFWHM: the project against napari-psf-analysis (measured) or the truth "
          "(simulated); medians over the beads; _x: the median of the per-bead ratios")
    print(table(rows, cols))


if __name__ == "__main__":
    main()
