"""The smooth part of the sparse + smooth deblur: nodes every ``step`` pixels, bilinear
between them (``u = U w``), the adjoint, and the nodes' graph Laplacian."""

from __future__ import annotations

import numpy as np

from ..model.psf_field import interp_matrix


class SmoothGrid:
    """``u = U w``: bilinear interpolation of nodes every ``step`` pixels; its adjoint;
    and the nodes' graph Laplacian (symmetric, norm <= 8)."""

    def __init__(self, shape: tuple[int, int], step: float) -> None:
        h, w = shape
        self.shape = (int(h), int(w))
        ny = max(2, int(np.ceil((h - 1) / step)) + 1)
        nx = max(2, int(np.ceil((w - 1) / step)) + 1)
        self.nodes = (np.linspace(0, h - 1, ny), np.linspace(0, w - 1, nx))
        self.ry = interp_matrix(self.nodes[0], h).astype(np.float32).tocsr()  # (H, ny)
        self.rx = interp_matrix(self.nodes[1], w).astype(np.float32).tocsr()  # (W, nx)
        self.ryt, self.rxt = self.ry.T.tocsr(), self.rx.T.tocsr()
        # synthesis as dense products (BLAS): faster than the sparse ones (bench_deblur_speed)
        self._ry_dense = self.ry.toarray()
        self._rxt_dense = np.ascontiguousarray(self.rxt.toarray())  # (nx, W)
        self.step = float(max((h - 1) / (ny - 1), (w - 1) / (nx - 1)))

    @property
    def grid_shape(self) -> tuple[int, int]:
        return (len(self.nodes[0]), len(self.nodes[1]))

    def synthesis(self, w: np.ndarray) -> np.ndarray:
        """``U w``: (ny, nx) -> (H, W)."""
        a = self._ry_dense @ np.asarray(w, np.float32)  # (H, nx)
        return a @ self._rxt_dense

    def adjoint(self, g: np.ndarray) -> np.ndarray:
        """``U^T g``: (H, W) -> (ny, nx)."""
        a = self.ryt @ g  # (ny, W)
        return np.ascontiguousarray((self.rxt @ a.T).T)

    @staticmethod
    def laplacian(w: np.ndarray) -> np.ndarray:
        """Graph Laplacian of the nodes (4 neighbours, none across the border)."""
        out = np.zeros_like(w)
        out[1:] += w[:-1] - w[1:]
        out[:-1] += w[1:] - w[:-1]
        out[:, 1:] += w[:, :-1] - w[:, 1:]
        out[:, :-1] += w[:, 1:] - w[:, :-1]
        return out

    def norm2(self) -> float:
        """``||U||^2`` (exact: the largest eigenvalues of the small ``R^T R``)."""
        ey = np.linalg.eigvalsh((self.ryt @ self.ry).toarray()).max()
        ex = np.linalg.eigvalsh((self.rxt @ self.rx).toarray()).max()
        return float(ey * ex)


__all__ = ["SmoothGrid"]
