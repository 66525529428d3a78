"""The paper's identification of an image's operator in its family's cone (Appendix D).

The family's operators are ``H u = sum_ij Gamma[i, j] h_i * (a_j . u)`` with ``Gamma`` in
the cone of the ``Gamma_k``. Each bead ``p`` of the image, centred and free of background,
gives its coefficients ``c_p = <p_p, h_i>``; problem (9) is

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

#: Default range of the beads' amplitudes relative to the family's (patches are
#: normalised to unit flux, so 1 is a bead whose flux was measured exactly).
AMPLITUDE_RANGE = (0.5, 2.0)


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


def identify_gamma(c: np.ndarray, at: np.ndarray, gammas: np.ndarray, *,
                   amplitude_range=AMPLITUDE_RANGE, max_iter: int = 100
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """The paper's problem (9): ``Gamma`` (I, J) in the cone of the ``Gamma_k`` that
    explains the beads' coefficients ``c`` (P, I) at their spatial basis values ``at``
    (P, J).

    Returns
    -------
    gamma : ndarray of shape (I, J)
    weights : ndarray of shape (K,)
    amplitudes : ndarray of shape (P,)
    objective : list of float
    """
    v = np.einsum("pj,kij->kpi", at, gammas)  # (K, P, I)
    lam, g, history = solve_identification(c, v, amplitude_range=amplitude_range,
                                           max_iter=max_iter)
    return np.tensordot(lam, gammas, axes=1), lam, g, history
