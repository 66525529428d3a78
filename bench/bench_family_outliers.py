"""The family's outlier test: good beads kept at the rim, bad patches rejected.

    python bench/bench_family_outliers.py [--generators ours pyotf psfmodels]
        [--seeds 0 1 2] [--cache DIR] [--data ../shared/data]

Per scene (``identify_scenes``: 10 training images of 1024 x 1024, 150 beads each, three
hidden conditions), the family's pooled patches get 10 doublets (a patch plus a copy of
itself shifted by a sixth to a quarter of the patch) and 10 noise patches put in at random
beads; the test then scores every patch. Its good beads are counted by where they sit
(``max(|u|, |v|)`` with ``u, v`` in [-1, 1] over the field): inner (< 0.5), middle, outer
(>= 0.8), on the patches as they are; the bad patches are scored among the others. Rows:

- ``loo sd 3``: each image's leave-one-out residuals of its thin-plate field over their
  mean and standard deviation, rejected above 3 (the test of one image's beads);
- ``robust T``: each image's standardized residuals over 1.4826 times their median
  absolute deviation, rejected above ``T`` (``learn_basis`` with ``groups``; the default
  ``T`` is :data:`~napari_psfspace.core.model.pca.GROUP_Z`).

Columns: the share of good beads rejected in each ring; the share of doublets and of noise
patches rejected. The measured sets (``--data``, the slices of ``bench_subspace_measured``)
get the same bad patches; their beads' positions are not known to be good, so the share of
their own beads rejected is shown as ``all``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

import napari_psfspace.core.family.estimate as family_estimate
from benchlib import table
from identify_scenes import make_scene
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.pca import GROUP_Z
from napari_psfspace.core.model.tps import ThinPlateSpline
from napari_psfspace.io import read_image

THRESHOLDS = (4.0, 6.0, 8.0, GROUP_Z, 15.0)
N_BAD = 10  # doublets, and as many noise patches


def scores(learn_basis):
    """A stand-in for the family's ``learn_basis`` that puts the bad patches in, records
    both tests' scores, and learns from the patches as given."""
    found = []

    def wrapped(psfs, n_psf, **kw):
        clean = np.array(psfs, dtype=np.float64)
        pos, groups, support = kw["positions"], kw["groups"], kw["support"]
        rng = np.random.default_rng(len(clean))
        size = clean.shape[-1]
        bad = rng.choice(len(clean), 2 * N_BAD, replace=False)
        dirty = clean.copy()
        for j, b in enumerate(bad[:N_BAD]):
            shift = int(rng.integers(size // 6, size // 4 + 1))
            dirty[b] = 0.5 * (clean[b] + np.roll(clean[b], shift, axis=j % 2))
        for b in bad[N_BAD:]:
            r = rng.uniform(0, 1, clean.shape[1:]) * support
            dirty[b] = r / r.sum()
        kind = np.zeros(len(clean), int)  # 0 good, 1 doublet, 2 noise
        kind[bad[:N_BAD]], kind[bad[N_BAD:]] = 1, 2
        rec = {"kind": kind, "pos": pos}
        for tag, x in (("clean", clean), ("dirty", dirty)):
            rec[f"robust_{tag}"] = learn_basis(x, n_psf, **{**kw, "z_threshold": np.inf}
                                               ).zscores
            rec[f"loo_{tag}"] = _loo_scores(x, n_psf, kw.get("weights"), support, pos,
                                          groups)
        found.append(rec)
        return learn_basis(psfs, n_psf, **kw)

    return wrapped, found


def _loo_scores(x, n_psf, w, support, pos, groups) -> np.ndarray:
    """The one-image test's scores: each image's leave-one-out residuals of the thin-plate
    fields of the first components (``n_psf`` when it is given, else five), over their mean
    and standard deviation."""
    x = x[:, support]
    norms = np.linalg.norm(x, axis=1)
    xn = x / norms[:, None] if w is None else x * np.sqrt(w / np.mean(w * norms**2))[:, None]
    vt = np.linalg.svd(xn, full_matrices=False)[2]
    coef = xn @ vt[:n_psf if isinstance(n_psf, int) else 5].T
    out = np.zeros(len(x))
    for g in np.unique(groups):
        sel = groups == g
        if np.count_nonzero(sel) >= 4:
            r = ThinPlateSpline(pos[sel], coef[sel]).loo_residuals
            sd = r.std(axis=0)
            sd[sd == 0] = 1.0
            out[sel] = (np.abs(r - r.mean(axis=0)) / sd).max(axis=1)
    return out


def learn(images, r, **kw) -> list[dict]:
    wrapped, found = scores(family_estimate.learn_basis)
    original = family_estimate.learn_basis
    family_estimate.learn_basis = wrapped
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            estimate_family(images, psf_radius=r, **kw)
    finally:
        family_estimate.learn_basis = original
    # the PCA of all the family's patches (its choices also learn from some images only)
    return [max(found, key=lambda f: len(f["kind"]))]


def rows_of(name, found, shape) -> list[dict]:
    z = {k: np.concatenate([f[k] for f in found])
         for k in ("robust_clean", "robust_dirty", "loo_clean", "loo_dirty", "kind")}
    where = np.concatenate([np.abs(f["pos"] / (np.asarray(shape) / 2.0) - 1.0).max(axis=1)
                            for f in found])
    good = z["kind"] == 0
    rings = {"inner": good & (where < 0.5), "middle": good & (where >= 0.5) & (where < 0.8),
             "outer": good & (where >= 0.8), "all": good}
    out = []
    for test, key, thresholds in (("loo sd", "loo", (3.0,)), ("robust", "robust", THRESHOLDS)):
        for t in thresholds:
            out.append({"scenes": name, "test": f"{test} {t:g}",
                        **{ring: float(np.mean(z[key + "_clean"][m] > t)) if m.any()
                           else None for ring, m in rings.items()},
                        "doublets": float(np.mean(z[key + "_dirty"][z["kind"] == 1] > t)),
                        "noise": float(np.mean(z[key + "_dirty"][z["kind"] == 2] > t))})
    return out


MEASURED = {
    # name: (file under the data folder, first slice, last slice + 1, PSF radius in px)
    "sp8_confocal": ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", 26, 39, None),
    "astigmatic": ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", 27, 39, 10.0),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generators", nargs="+", default=["ours", "pyotf", "psfmodels"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--cache", default=None, help="a folder keeping the rendered scenes")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared"
                                          / "data"))
    args = ap.parse_args()
    rows = []
    for gen in args.generators:
        found = []
        for seed in args.seeds:
            try:
                sc = make_scene(seed, generator=gen, cache=args.cache)
            except ValueError as exc:  # a scene whose beads do not fit its field
                print(f"{gen} seed {seed}: skipped ({exc})", flush=True)
                continue
            shape = sc.train[0].shape
            found += learn(sc.train, sc.psf_radius)
            print(f"{gen} seed {seed}: {sum(len(f['kind']) for f in found)} patches",
                  flush=True)
        if found:
            rows += rows_of(f"{gen} {len(found)} seeds", found, shape)
    data = Path(args.data)
    for name, (rel, a, b, r) in MEASURED.items():
        path = data / rel
        if not path.exists():
            print(f"{name}: {path} not found, skipped")
            continue
        slices = [read_image(path, index=z)[0] for z in range(a, b)]
        if r is None:
            r = 0.5 / read_image(path, index=a)[1].pixel_size
        rows += [q for q in rows_of(name, learn(slices, r), slices[0].shape)]
    print("\nThe family's outlier test: share of good beads rejected by ring (inner < 0.5 <= "
          "middle < 0.8 <= outer), and of the doublets and noise patches put in")
    print(table(rows, [("scenes", "s"), ("test", "s"), ("inner", ".3f"), ("middle", ".3f"),
                       ("outer", ".3f"), ("all", ".3f"), ("doublets", ".2f"),
                       ("noise", ".2f")]))


if __name__ == "__main__":
    main()
