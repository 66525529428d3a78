"""The size ``I`` of a family's PSF basis, chosen from the data.

The Gavish-Donoho rule assumes white noise of one level. The family's patches are
Wiener-filtered and their noise varies from bead to bead: on faint stacks the rule on
them keeps dozens of PSF components, most of them noise, and the family's operators are
worse than each image's own (``bench/bench_subspace.py --noise``). :func:`white_rank`
applies the rule to the raw patches whitened by each bead's noise instead: fewer
components the fainter the stack, and the family beats one image at a time there.

Tried, not kept: choosing ``I`` and ``J`` by 5-fold cross-validation over each image's
beads (the closed-form held-out residual of ``Gamma_k a(x)`` inside the cone, amplitude
fitted). It chose too small a model wherever an image has few beads (``I = J = 1`` on
7-bead images): taking one bead of six out changes an image's maps more than the sizes
do. ``J`` by cross-validation was worse than the rule on the maps on most stacks
(``bench/bench_subspace.py``).
"""

from __future__ import annotations

import numpy as np

from ..model.pca import rank_by_threshold


def white_rank(psf: np.ndarray, noise_sd: np.ndarray, window: np.ndarray, *,
               core: float = 0.5) -> int:
    """Gavish-Donoho rank of the patches whitened by their noise.

    Parameters
    ----------
    psf : ndarray of shape (N, P, P)
        Raw (not denoised) windowed sum-1 patches.
    noise_sd : ndarray of shape (N,)
        Per-pixel noise of each patch (the image's noise over the bead's flux).
    window : ndarray of shape (P, P)
        The window the patches were multiplied by.
    core : float
        Only pixels where the window exceeds this enter (the noise there is
        ``noise_sd * window``, divided out).

    Returns
    -------
    int
        Number of singular values of the whitened patches above the rule's threshold.
    """
    sel = np.asarray(window) > core
    sd = np.asarray(noise_sd, float).copy()
    good = np.isfinite(sd) & (sd > 0)
    if not good.any():  # no noise measured (e.g. a flat 8-bit background): unwhitened
        sd[:] = 1.0
    else:  # a bead whose background's MAD is 0 takes the typical noise
        sd[~good] = np.median(sd[good])
    x = psf[:, sel] / (sd[:, None] * window[sel])
    s = np.linalg.svd(x, compute_uv=False)
    return rank_by_threshold(s, x.shape)[0]
