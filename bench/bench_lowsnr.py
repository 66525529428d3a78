"""Low signal per pixel: what limits the field error at peak SNR 7 (issue 9).

    python bench/bench_lowsnr.py

On `bench_accuracy.py`'s noise-level scenes (1024x1024, 150 beads, moderate
aberrations, bead photons x0.05 and x0.1: peak SNR 7 and 11) it compares, by the
aligned field error against the truth (8x8 grid):

- ``estimate``: `estimate_operator` as it stands (basis size by held-out beads);
- ``pca I=k``: the same with the basis size forced;
- ``mean only``: one PSF, the noise-weighted mean of the band-limited patches, refitted
  to the raw patches (`denoise.refit_basis`) through the thin-plate field;
- ``taylor k``: that mean PSF and ``k`` of its spatial derivatives (orders 2, 3, 4:
  widening, astigmatism, coma-like changes) as the basis; each bead's coefficients by
  projection of its band-limited patch, then the same field and refit. No basis image
  is learnt from the beads' noise beyond the mean.
- ``oracle: true basis I=k``: the truth's own PSF basis (the first ``k`` components of
  the PCA of the noise-free PSFs at the detected beads), so that no basis image carries
  any noise; only each bead's coefficients come from its (band-limited) noisy patch, then
  the same thin-plate field (smoothing by GCV). Any basis learnt from the same beads adds
  its own noise to this: the error of a method of the paper's class (PCA basis,
  thin-plate field) cannot be much below it.

After each table, the centring: the beads' centring error against the truth (rms, px)
and how much that jitter alone blurs the mean PSF (the noise-free PSFs at the true
positions, shifted by each bead's error, averaged): if the mean's excess error were the
centring's, better centring could lower it; it is noise.

``noise of the mean``: the mean PSF's own noise, the beads' held-out residual over the
number of beads (sqrt(residual / K)); ``SI`` the best single PSF's error (the truth's
mean): a spatially varying model must beat it to help.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from benchlib import table
from napari_psfspace.core.beads.window import radial_distance
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model.denoise import band_limit, refit_basis
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.model.field import fit_field
from napari_psfspace.core.model.pca import PsfBasis, learn_basis
from napari_psfspace.core.simulation import simulate_beads
from napari_psfspace.core.simulation.metrics import evaluate_against_truth

ORDERS = [(2, 0), (0, 2), (1, 1), (3, 0), (2, 1), (1, 2), (0, 3), (4, 0), (0, 4), (2, 2)]


def taylor_operator(est, shape, n_terms: int):
    """The mean PSF and ``n_terms`` of its derivatives as the basis, through the field."""
    pt = est.patches
    p = pt.psf.shape[-1]
    sd = pt.noise / pt.flux
    window = (radial_distance(p) <= pt.r_ext).astype(float)
    filt, _ = band_limit(pt.psf, sd, window)
    w = 1.0 / (pt.psf**2).sum(axis=(1, 2))
    h0 = (filt * w[:, None, None]).sum(0) / w.sum()
    k = np.fft.fftfreq(p) * 2 * np.pi
    ky, kx = np.meshgrid(k, k, indexing="ij")
    spec = np.fft.fft2(np.fft.ifftshift(h0))
    images = [h0] + [np.real(np.fft.fftshift(np.fft.ifft2(spec * (1j * kx) ** a
                                                          * (1j * ky) ** b)))
                     for a, b in ORDERS[:n_terms]]
    q, _ = np.linalg.qr(np.array(images).reshape(len(images), -1).T)
    basis = q.T.reshape(-1, p, p)
    coef = filt.reshape(len(filt), -1) @ q
    n = len(coef)
    b = PsfBasis(basis, coef, np.ones(n, bool), np.zeros(n), np.zeros(0), float("nan"),
                 len(basis))

    def refit(a):
        return refit_basis(pt.psf, a, sd, window, weights=w, prior=basis)[0]

    op, _, _ = fit_field(b, pt, shape, refit=refit)
    return op


def true_basis_operator(est, truth, shape, n_psf: int):
    """The oracle row: the noise-free truth's PCA basis, the beads' noisy coefficients."""
    pt = est.patches
    p = pt.psf.shape[-1]
    window = (radial_distance(p) <= pt.r_ext).astype(float)
    clean = np.array([truth.psf_at(y, x, p) for y, x in pt.centers]) * window
    clean /= clean.sum(axis=(1, 2), keepdims=True)
    filt, _ = band_limit(pt.psf, pt.noise / pt.flux, window)
    b = learn_basis(clean, n_psf, positions=pt.centers)
    coef = filt.reshape(len(filt), -1) @ b.basis.reshape(n_psf, -1).T
    b = dataclasses.replace(b, coefficients=coef, inliers=np.ones(len(coef), bool))
    return fit_field(b, pt, shape)[0]


def centring_lines(est, truth) -> str:
    """The centring error and the blur its jitter alone gives the mean PSF."""
    from scipy import ndimage as ndi

    pt = est.patches
    p = pt.psf.shape[-1]
    d = np.hypot(*(pt.centers[:, None, :] - truth.positions[None]).transpose(2, 0, 1))
    true = truth.positions[d.argmin(axis=1)]
    err = pt.centers - true
    rms = float(np.sqrt((err**2).sum(axis=1).mean()))
    err = err - err.mean(axis=0)  # a common offset is no blur (the error is aligned)
    clean = np.array([truth.psf_at(y, x, p) for y, x in true])
    jit = np.array([ndi.shift(c, -e, order=3, mode="constant")
                    for c, e in zip(clean, err, strict=True)])
    m0, m1 = clean.mean(axis=0), jit.mean(axis=0)
    m0, m1 = m0 / m0.sum(), m1 / m1.sum()
    blur = float(np.linalg.norm(m1 - m0) / np.linalg.norm(m0))
    return (f"centring error {rms:.3f} px rms; its jitter alone blurs the mean PSF by "
            f"{blur:.4f} (relative l2)")


def main():
    rows = []
    for factor in (0.05, 0.1):
        image, truth = simulate_beads((1024, 1024), 150, aberrations="moderate", seed=0,
                                      amplitude=(2e4 * factor, 6e4 * factor))
        base = {"photons": f"x{factor:g}", "peak_snr": float(np.median(truth.peak_snr))}
        est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius))
        ev = evaluate_against_truth(est.operator, truth, 8)
        k = len(est.patches.psf)
        held = est.operator.metadata["heldout"]["residual_mean"]
        common = {**base, "SI": ev["shift_invariant"]["mean"],
                  "noise_of_mean": float(np.sqrt(held / k))}
        rows.append({**common, "model": f"estimate (I={est.operator.n_psf})",
                     "aligned": ev["aligned"]["mean"]})
        for i in (3, 6):
            e = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius, n_psf=i))
            err = evaluate_against_truth(e.operator, truth, 8)["aligned"]["mean"]
            rows.append({**common, "model": f"pca I={i}", "aligned": err})
        one = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius, n_psf=1))
        for n in (0, 3, 7, 10):
            op = taylor_operator(one, image.shape, n)
            rows.append({**common, "model": "mean only" if n == 0 else f"taylor {n}",
                         "aligned": evaluate_against_truth(op, truth, 8)["aligned"]["mean"]})
        for i in (2, 3, 4, 6):
            op = true_basis_operator(one, truth, image.shape, i)
            rows.append({**common, "model": f"oracle: true basis I={i}",
                         "aligned": evaluate_against_truth(op, truth, 8)["aligned"]["mean"]})
        print(table(rows[-11:], [("photons", "s"), ("peak_snr", ".0f"), ("model", "s"),
                                ("aligned", ".4f"), ("SI", ".4f"),
                                ("noise_of_mean", ".4f")]), flush=True)
        print(centring_lines(one, truth))
        print()


if __name__ == "__main__":
    main()
