"""Identify the operator of one blurred image from a few of its beads (paper, Appendix D).

A family of operators (:class:`~napari_psfspace.core.subspace.OperatorSubspace`) is known:
``H u = sum_ij Gamma[i, j] h_i * (a_j . u)`` with ``Gamma`` in the cone of the ``Gamma_k``.
Each bead ``p`` of the image, centred and free of background, gives its coefficients
``c_p = <p_p, h_i>``; problem (9) is

    min_{Gamma in C, g in [a, b]^P}  1/2 sum_p || g_p Gamma a(z_p) - c_p ||^2,

with ``g_p`` the unknown amplitude of bead ``p``. It is solved by alternating minimisation,
each step exactly:

- ``Gamma`` given ``g``: every ``Gamma`` of the cone is ``sum_k lambda_k Gamma_k`` with
  ``lambda >= 0``, and ``Gamma a(z_p)`` is linear in ``lambda``: a non-negative least
  squares problem in ``K`` unknowns (``scipy.optimize.nnls``, exact). The paper uses an
  accelerated projected gradient here; an exact solver of a K-unknown problem needs no
  step size or iteration count.
- ``g`` given ``Gamma``: each ``g_p`` is a one-dimensional least squares clipped to
  ``[a, b]``, in closed form.

``P >= J`` beads should identify ``Gamma`` (each bead gives ``I`` equations); with fewer,
the cone alone keeps it plausible.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from ..common.validate import as_image
from ..model.heldout import heldout_residuals
from ..model.operator import ProductConvolution
from ..subspace.patches import image_patches
from ..subspace.result import OperatorSubspace, space_at

#: Default range of the beads' amplitudes relative to the family's (patches are
#: normalised to unit flux, so 1 is a bead whose flux was measured exactly).
AMPLITUDE_RANGE = (0.5, 2.0)


def _coefficients(psf: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (P, I) of patches (P, S, S) on the basis (I, S, S) (the
    refitted basis images are not exactly orthonormal)."""
    b = basis.reshape(len(basis), -1)
    return np.linalg.lstsq(b.T, psf.reshape(len(psf), -1).T, rcond=None)[0].T


def solve_identification(c: np.ndarray, v: np.ndarray, *,
                         amplitude_range: tuple[float, float] = AMPLITUDE_RANGE,
                         max_iter: int = 100, tol: float = 1e-8
                         ) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Problem (9) in the cone's weights.

    Parameters
    ----------
    c : ndarray of shape (P, I)
        Coefficients of the beads' patches.
    v : ndarray of shape (K, P, I)
        ``Gamma_k a(z_p)``: the coefficients image ``k``'s operator has at each bead.
    amplitude_range : (float, float)
        ``[a, b]``, ``0 < a <= 1 <= b``.
    max_iter, tol
        Alternations at most; stop when the objective changes by less than ``tol``
        relatively.

    Returns
    -------
    weights : ndarray of shape (K,)
        ``lambda >= 0``: ``Gamma = sum_k lambda_k Gamma_k``.
    amplitudes : ndarray of shape (P,)
    objective : list of float
        ``1/2 sum_p ||g_p Gamma a(z_p) - c_p||^2`` after each alternation.
    """
    a, b = (float(x) for x in amplitude_range)
    if not 0 < a <= 1 <= b:
        raise ValueError(f"`amplitude_range` must be (a, b) with 0 < a <= 1 <= b, got "
                         f"{amplitude_range!r}")
    n_k, n_p, n_i = v.shape
    g = np.ones(n_p)
    history: list[float] = []
    lam = np.zeros(n_k)
    for _ in range(int(max_iter)):
        m_mat = (g[None, :, None] * v).reshape(n_k, n_p * n_i).T  # (P I, K)
        lam, _ = nnls(m_mat, c.ravel(), maxiter=50 * n_k)
        m = np.tensordot(lam, v, axes=1)  # (P, I)
        mm = (m * m).sum(axis=1)
        g = np.where(mm > 0, (m * c).sum(axis=1) / np.maximum(mm, 1e-300), 1.0).clip(a, b)
        history.append(0.5 * float(((g[:, None] * m - c) ** 2).sum()))
        if len(history) > 1 and abs(history[-2] - history[-1]) <= tol * max(history[-2],
                                                                           1e-300):
            break
    return lam, g, history


def identify_operator(
    image: np.ndarray,
    subspace: OperatorSubspace,
    *,
    beads: np.ndarray | None = None,
    psf_radius: float | None = None,
    threshold: float = 8.0,
    amplitude_range: tuple[float, float] = AMPLITUDE_RANGE,
    max_iter: int = 100,
) -> ProductConvolution:
    """The operator of the family that explains the beads of one image (problem (9)).

    Parameters
    ----------
    image : ndarray of shape (H, W)
        The blurred image, of the shape the family was learnt on.
    subspace : OperatorSubspace
        The family of operators (:func:`~napari_psfspace.core.subspace.estimate_subspace`).
    beads : ndarray of shape (N, 2), optional
        Bead positions (row, column), pixels, e.g. a Points layer's; they are centred
        sub-pixel and checked (border, neighbours, saturation). Default: detected.
    psf_radius : float, optional
        Patch radius, pixels; default the family's (it must give the family's patch
        size).
    threshold : float
        Detection threshold (noise standard deviations), when ``beads`` is None.
    amplitude_range : (float, float)
        ``[a, b]``: range of each bead's amplitude relative to the family's.
    max_iter : int
        Alternations at most.

    Returns
    -------
    ProductConvolution
        Its PSFs lie in the family's cone and sum to 1. ``metadata["identification"]``
        holds ``gamma`` (I, J), the cone ``weights`` (K,), the beads' ``positions`` and
        ``amplitudes``, the ``objective`` history, ``n_beads``, and how well the
        operator fits those beads: the median relative residual of their patches, its
        noise floor, and ``model_error = sqrt(median residual^2 - median floor^2)``, the
        relative error of the operator beyond the noise (which
        :func:`~napari_psfspace.core.restore.deconvolve.deblur` allows for).

    Raises
    ------
    ValueError
        An image of another shape than the family's, a radius giving another patch size,
        bad bead positions, or no usable bead.
    """
    img = as_image(image)
    if tuple(img.shape) != tuple(subspace.shape):
        raise ValueError(f"`image` has shape {tuple(img.shape)}, but the family was learnt "
                         f"on images of shape {tuple(subspace.shape)}: identify with a "
                         "family of this image size")
    r = float(psf_radius if psf_radius is not None
              else subspace.metadata.get("psf_radius", np.nan))
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"`psf_radius` must be a positive number of pixels (the family "
                         f"does not record one), got {psf_radius!r}")
    found = image_patches(image, r, threshold=threshold, positions=beads)
    if found.patches is None:
        raise ValueError(f"no usable bead in `image` to identify its operator: "
                         f"{found.summary}")
    patches = found.patches
    size = subspace.basis.shape[1]
    if patches.psf.shape[1] != size:
        raise ValueError(f"`psf_radius` = {r:g} px gives {patches.psf.shape[1]} px patches; "
                         f"the family's PSFs are {size} px: use the family's radius "
                         f"({subspace.metadata.get('psf_radius')})")
    c = _coefficients(patches.psf, subspace.basis)  # (P, I)
    at = space_at(subspace.space, subspace.grid, patches.centers)  # (P, J)
    v = np.einsum("pj,kij->kpi", at, subspace.gammas)  # (K, P, I)
    lam, g, history = solve_identification(c, v, amplitude_range=amplitude_range,
                                           max_iter=max_iter)
    if not lam.any():
        raise ValueError("the beads' PSFs lie outside the family's cone (every weight is "
                         "0): is this image from the same microscope and PSF radius?")
    gamma = np.tensordot(lam, subspace.gammas, axes=1)
    op = subspace.operator_from(gamma, project=False)
    fit = heldout_residuals(op, patches)  # on the beads it was identified from
    excess = float(np.median(fit.residual ** 2) - np.median(fit.noise_floor ** 2))
    meta = {"identification": {
        "model_error": float(np.sqrt(max(excess, 0.0))),
        "residual_median": float(np.median(fit.residual)),
        "noise_floor_median": float(np.median(fit.noise_floor)),
        "gamma": gamma.tolist(), "weights": lam.tolist(),
        "positions": patches.centers.tolist(), "amplitudes": g.tolist(),
        "objective": history, "n_beads": int(len(c)), "n_space": subspace.n_space,
        "enough_beads": bool(len(c) >= subspace.n_space), "beads_table": found.summary}}
    return ProductConvolution(op.basis, op.coefficients, shape=op.shape, grid=op.grid,
                              metadata=meta)
