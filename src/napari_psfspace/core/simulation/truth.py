"""What a simulation knows exactly: :class:`SimulationTruth`, the bead positions,
amplitudes and diameters, the optics and the aberration field, and the true PSF at any
field position (with the bead-size and drift filters the image was made with).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .aberrations import FieldAberrations
from .optics import Optics, check_size, object_pad, psf_stack


@dataclass(eq=False)
class SimulationTruth:
    """Ground truth of a :func:`simulate_beads` image.

    Attributes
    ----------
    shape : tuple of int
        ``(H, W)`` of the image.
    positions : ndarray, shape (M, 2), float64
        True bead centres ``(row, col)`` in pixels (pixel centres at integers).
    amplitudes : ndarray, shape (M,), float64
        Total photons emitted by each bead and collected (integral of its PSF
        times amplitude over the plane).
    background : ndarray, shape (H, W), float32
        Smooth background, photons per pixel.
    optics : Optics
    aberrations : FieldAberrations
    gain : float
        Camera gain, ADU per photo-electron.
    offset : float
        Camera offset, ADU.
    read_noise : float
        Read noise, electrons rms.
    psf_radius : int
        Recommended PSF radius ``r`` (pixels) for the estimator: the radius of
        the disk holding ``psf_energy`` (default 90 %) of the energy of the
        widest PSF in the field (corners, edge middles, centre), rounded up,
        at least 4.
    peak_snr : ndarray, shape (M,)
        Per-bead peak SNR ``peak / sqrt(peak + background + read_noise^2)``
        with ``peak`` the expected photons in the brightest pixel of the bead,
        in photo-electrons.
    effects : dict
        Ground truth of the injected effects (see the ``effects`` parameter
        of :func:`simulate_beads`): each switched-on effect's parameter under
        its own key plus the arrays that define it. Empty without effects.
    """

    shape: tuple[int, int]
    positions: np.ndarray
    amplitudes: np.ndarray
    background: np.ndarray
    optics: Optics
    aberrations: FieldAberrations
    gain: float
    offset: float
    read_noise: float
    psf_radius: int
    peak_snr: np.ndarray
    effects: dict[str, Any] = field(default_factory=dict)

    def _psfs(self, ys: np.ndarray, xs: np.ndarray, size: int | None) -> np.ndarray:
        """Centred true PSFs at ``(ys, xs)`` (flat arrays), each normalised to sum 1."""
        size = check_size(2 * self.psf_radius + 1 if size is None else size)
        coefs = self.aberrations.coefficient_matrix(ys, xs, self.shape)
        psfs = psf_stack(
            self.aberrations.noll_indices, coefs, np.zeros((len(ys), 2)), self.optics, size
        )
        return psfs / psfs.sum(axis=(-2, -1), keepdims=True)

    def psf_at(self, y: float, x: float, size: int | None = None) -> np.ndarray:
        """True PSF at field position ``(y, x)`` (pixels).

        Parameters
        ----------
        y, x : float
            Row and column of the field position, pixels.
        size : int or None
            Odd window side; default ``2 * psf_radius + 1``.

        Returns
        -------
        ndarray, shape (size, size), float64
            PSF centred on pixel ``size // 2`` (no sub-pixel shift), normalised
            to sum 1 over the window.
        """
        return self._psfs(np.array([float(y)]), np.array([float(x)]), size)[0]

    def observed_psf_at(
        self, y: float, x: float, size: int | None = None, *, diameter: float | None = None
    ) -> np.ndarray:
        """Image of a bead at ``(y, x)`` as the camera sees it, apart from noise.

        The optical PSF (:meth:`psf_at`) convolved with the projected bead
        profile and averaged along the drift, when those effects were
        simulated; camera effects (illumination, nonlinearity, offsets, hot
        pixels, saturation) are not included.

        Parameters
        ----------
        y, x : float
            Row and column of the field position, pixels.
        size : int or None
            Odd window side; default ``2 * psf_radius + 1``.
        diameter : float or None
            Bead diameter, µm; default the mean simulated diameter (0 without
            the ``"bead_size"`` effect).

        Returns
        -------
        ndarray, shape (size, size), float64
            Centred on pixel ``size // 2``, normalised to sum 1 over the window.
            Equals :meth:`psf_at` for point beads without drift.
        """
        if diameter is None:
            diameter = float(np.mean(self.effects.get("bead_size", (0.0, 0.0))))
        diameter = float(diameter)
        if not np.isfinite(diameter) or diameter < 0:
            raise ValueError(f"diameter must be >= 0 and finite, got {diameter!r}")
        drift = self.effects.get("drift")
        if diameter == 0 and drift is None:
            return self.psf_at(y, x, size)
        size = check_size(2 * self.psf_radius + 1 if size is None else size)
        diameters = np.array([diameter]) if diameter > 0 else None
        pad = object_pad(self.optics, diameters, drift)
        coefs = self.aberrations.coefficient_matrix(float(y), float(x), self.shape)[None]
        psf = psf_stack(
            self.aberrations.noll_indices,
            coefs,
            np.zeros((1, 2)),
            self.optics,
            size + 2 * pad,
            diameters=diameters,
            drift=drift,
        )[0]
        psf = psf[pad : pad + size, pad : pad + size]
        return psf / psf.sum()

    def psf_grid(
        self,
        n_rows: int = 8,
        n_cols: int = 8,
        size: int | None = None,
        margin: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True PSFs on a regular grid of field positions.

        Parameters
        ----------
        n_rows, n_cols : int
            Number of grid rows and columns.
        size : int or None
            Odd window side; default ``2 * psf_radius + 1``.
        margin : float or None
            Distance (pixels) of the outermost positions from the border pixel
            centres; default ``psf_radius``.

        Returns
        -------
        ys : ndarray, shape (n_rows,)
            Row positions, pixels, evenly spaced in ``[margin, H - 1 - margin]``.
        xs : ndarray, shape (n_cols,)
            Column positions, pixels.
        psfs : ndarray, shape (n_rows, n_cols, size, size)
            ``psfs[i, k] == psf_at(ys[i], xs[k], size)``.
        """
        margin = float(self.psf_radius if margin is None else margin)
        ys = np.linspace(margin, self.shape[0] - 1 - margin, n_rows)
        xs = np.linspace(margin, self.shape[1] - 1 - margin, n_cols)
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        psfs = self._psfs(yy.ravel(), xx.ravel(), size)
        return ys, xs, psfs.reshape(n_rows, n_cols, *psfs.shape[-2:])
