"""A learnt family of operators: :class:`OperatorFamily` (section 2.4).

The operator of condition ``k`` is ``H_k u = sum_ij Gamma_k[i, j] h_i * (a_j . u)``: a PSF
basis ``h_i`` (I, P, P), a basis of spatial variations ``a_j`` sampled on the coarse grid
the single operator uses (J, gy, gx), and one small matrix ``Gamma_k`` (I, J) per image.
The family is the cone of the ``Gamma_k`` (section 2.5): :meth:`project` brings any
``Gamma`` into it, :meth:`operator_from` builds its operator.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ..common.validate import check_int
from ..model.cone import Cone, project_onto_cone
from ..model.field import assemble_operator
from ..model.operator import ProductConvolution
from ..model.operator_checks import MAX_PSF_L1, check_model_field
from ..model.psf_field import interp_weights
from .choice import blend
from .family_file import read_family, write_family


def space_at(space: np.ndarray, grid, points: np.ndarray) -> np.ndarray:
    """The spatial basis at positions by bilinear interpolation between the nodes.

    Parameters
    ----------
    space : ndarray of shape (J, gy, gx)
    grid : (ndarray (gy,), ndarray (gx,))
        Node coordinates, pixels.
    points : ndarray of shape (n, 2)
        Positions (row, column), pixels.

    Returns
    -------
    ndarray of shape (n, J)
    """
    gy, gx = grid
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    j0, j1, ty = interp_weights(gy, pts[:, 0])
    k0, k1, tx = interp_weights(gx, pts[:, 1])
    a = space
    out = ((1 - ty) * ((1 - tx) * a[:, j0, k0] + tx * a[:, j0, k1])
           + ty * ((1 - tx) * a[:, j1, k0] + tx * a[:, j1, k1]))
    return out.T


@dataclass
class OperatorFamily:
    """Bases ``h_i`` and ``a_j``, one ``Gamma_k`` per image, and the cone they span.

    Attributes
    ----------
    basis : ndarray of shape (I, P, P)
        PSF basis ``h_i`` (orthonormal, learnt from the patches of all images).
    space : ndarray of shape (J, gy, gx)
        Spatial basis ``a_j`` on the coarse grid (orthonormal over the grid's nodes).
    grid : (ndarray (gy,), ndarray (gx,))
        Node coordinates, pixels (row, column).
    shape : (int, int)
        Image shape the operators act on.
    gammas : ndarray of shape (K, I, J)
        ``Gamma_k`` of each image.
    cone : Cone
        Reduced conic hull of the observed bead coefficients (the PSFs of every operator
        are kept inside it, as for one operator).
    grid_step : float
        The grid's largest spacing asked for, pixels (it gives back ``grid``).
    metadata : dict
        JSON-ready record (sizes, their choice, per-image bead counts and held-out
        errors, the operator kept for each image and why, timings).
    own : dict of int to ProductConvolution
        Single-image estimates of the images whose held-out beads asked for them
        (:mod:`.choice`).
    family_weights : ndarray of shape (K,), optional
        The family's weight ``w_k`` in each image's operator: :meth:`operator` gives
        image ``k`` the PSFs ``w_k h_family + (1 - w_k) h_own`` (1, or None for all: the
        family's operator alone, the paper's model). The ``Gamma_k`` place every image
        in the family whatever its weight (cone, condition coordinates, identification).
    """

    basis: np.ndarray
    space: np.ndarray
    grid: tuple[np.ndarray, np.ndarray]
    shape: tuple[int, int]
    gammas: np.ndarray
    cone: Cone
    grid_step: float = 32.0
    metadata: dict = field(default_factory=dict)
    own: dict = field(default_factory=dict)
    family_weights: np.ndarray | None = None
    _operators: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def n_psf(self) -> int:
        """``I``, the size of the PSF basis."""
        return int(self.basis.shape[0])

    @property
    def n_space(self) -> int:
        """``J``, the size of the spatial basis."""
        return int(self.space.shape[0])

    @property
    def n_images(self) -> int:
        """``K``, the number of images (conditions) learnt from."""
        return int(self.gammas.shape[0])

    def maps(self, gamma: np.ndarray) -> np.ndarray:
        """Coefficient maps ``sum_j Gamma[i, j] a_j`` on the grid, shape (I, gy, gx)."""
        g = np.asarray(gamma, dtype=np.float64).reshape(self.n_psf, self.n_space)
        return np.tensordot(g, self.space, axes=(1, 0))

    def operator_from(self, gamma: np.ndarray, *, project: bool = True,
                      metadata: dict | None = None) -> ProductConvolution:
        """The operator of a ``Gamma`` (I, J), projected onto the family's cone first.

        Its PSFs are kept inside the cone of observed PSFs and sum to 1 everywhere, as a
        single image's operator's are.
        """
        g = self.project(gamma) if project else np.asarray(gamma, dtype=np.float64)
        coarse = self.maps(g).reshape(self.n_psf, -1).T  # (G, I), nodes row-major
        op, _ = assemble_operator(self.basis, self.cone.generators, lambda nodes: coarse,
                                  self.shape, grid_step=self.grid_step, metadata=metadata,
                                  cone=self.cone, constraint="cone")
        return op

    def psfs_at(self, k: int, points: np.ndarray) -> np.ndarray:
        """The PSFs of image ``k``'s family operator at a few positions (n, 2), shape
        (n, P, P): as ``operator_from(gammas[k], project=False).psf_at``, keeping only
        the nodes around them in the cone (for judging the family on held-out beads
        without building the operator)."""
        return self.psfs_of(self.gammas[int(k)], points)

    def psfs_of(self, gamma: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The PSFs of the operator of ``Gamma`` (I, J) (unprojected) at a few positions
        (n, 2), shape (n, P, P), building only the nodes around them."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        coarse = self.maps(gamma).reshape(self.n_psf, -1).T
        op, _ = assemble_operator(self.basis, self.cone.generators, lambda nodes: coarse,
                                  self.shape, grid_step=self.grid_step, cone=self.cone, at=pts,
                                  constraint="cone")
        return np.array([op.psf_at(y, x) for y, x in pts]).reshape(
            len(pts), *self.basis.shape[1:])

    def operator(self, k: int) -> ProductConvolution:
        """The operator of image ``k`` of the stack learnt from: the family's, blended
        with the image's own estimate by its weight (:attr:`family_weights`).
        Built once and kept: make a new subspace rather than editing ``gammas`` in place.
        """
        k = check_int(k, "k", minimum=0, maximum=self.n_images - 1)
        w = self.family_weight(k)
        if w == 0.0:
            return self.own[k]
        if k not in self._operators:  # built once: psf_at(k, ...) in a loop stays cheap
            meta = {"subspace_image": k}
            op = self.operator_from(self.gammas[k], project=False, metadata=meta)
            if w < 1.0:
                op = blend(op, self.own[k], w, metadata={**meta, "family_weight": w})
            self._operators[k] = op
        return self._operators[k]

    def family_weight(self, k: int) -> float:
        """The family's weight in image ``k``'s operator (1: the family's alone)."""
        if self.family_weights is None or int(k) not in self.own:
            return 1.0
        return float(self.family_weights[int(k)])

    def project(self, gamma: np.ndarray) -> np.ndarray:
        """Euclidean projection of ``Gamma`` (I, J) onto the cone of the ``Gamma_k``."""
        g = np.asarray(gamma, dtype=np.float64)
        if g.size != self.n_psf * self.n_space:
            raise ValueError(f"`gamma` must have shape ({self.n_psf}, {self.n_space}), "
                             f"got {g.shape}")
        gens = self.gammas.reshape(self.n_images, -1)
        return project_onto_cone(g.reshape(1, -1), gens)[0].reshape(self.n_psf, self.n_space)

    def condition_coordinates(self, n: int = 2) -> np.ndarray:
        """The images' conditions as points: the first ``n`` principal coordinates of the
        ``Gamma_k`` (flattened, centred), shape (K, n); 0 beyond the family's rank.

        Images taken under close conditions lie close together; a drift of focus or
        temperature shows as a path.
        """
        g = self.gammas.reshape(self.n_images, -1)
        g = g - g.mean(axis=0)
        u, s, _ = np.linalg.svd(g, full_matrices=False)
        out = np.zeros((self.n_images, int(n)))
        m = min(int(n), len(s))
        out[:, :m] = u[:, :m] * s[:m]
        return out

    def psf_grids(self, n: int = 6, *, images=None) -> tuple[np.ndarray, np.ndarray,
                                                               np.ndarray]:
        """The PSFs of each image's operator at ``n x n`` field positions.

        Parameters
        ----------
        n : int
            Positions per side (as :meth:`ProductConvolution.psf_grid`).
        images : sequence of int, optional
            Which images; default all.

        Returns
        -------
        ys, xs : ndarray of shape (n,)
            Row and column of the positions, pixels.
        psfs : ndarray of shape (len(images), n, n, P, P)
        """
        ks = range(self.n_images) if images is None else [int(k) for k in images]
        grids = [self.operator(k).psf_grid(n, n) for k in ks]
        if not grids:
            raise ValueError("`images` must name at least one image")
        ys, xs, _ = grids[0]
        return ys, xs, np.stack([g[2] for g in grids])

    def psf_at(self, k: int, y: float, x: float) -> np.ndarray:
        """PSF (P, P), sum 1, of image ``k`` at pixel ``(y, x)``."""
        return self.operator(k).psf_at(y, x)

    def save(self, path) -> None:
        """Save to a ``.npz`` file (atomically, no pickle; ``docs/file-format.md``)."""
        arrays = {"basis": self.basis, "space": self.space,
                  "grid_y": self.grid[0], "grid_x": self.grid[1],
                  "shape": np.asarray(self.shape, dtype=np.int64),
                  "gammas": self.gammas, "cone": self.cone.generators,
                  "family_weights": (np.ones(self.n_images) if self.family_weights is None
                                     else np.asarray(self.family_weights, np.float64))}
        own = {}
        for k, op in self.own.items():
            if op.grid is None:
                raise ValueError(f"image {k}'s own operator must have coarse maps (a grid)")
            own[k] = {"basis": op.basis, "coefficients": op.coefficients,
                      "grid_y": op.grid[0], "grid_x": op.grid[1]}
        write_family(path, arrays, own, grid_step=self.grid_step,
                       metadata=self.metadata,
                       own_metadata={k: op.metadata for k, op in self.own.items()})

    @classmethod
    def load(cls, path) -> OperatorFamily:
        """Read a family written by :meth:`save`.

        Raises
        ------
        ValueError
            If the file is not a napari-psfspace family, has a newer format version, or
            holds inconsistent arrays (the message says which).
        FileNotFoundError
            If ``path`` does not exist.
        """
        arr, own_arrays, weights, header = read_family(path)
        shape = (int(arr["shape"][0]), int(arr["shape"][1]))
        meta = header.get("own_metadata", {})
        own = {}
        for k, a in own_arrays.items():
            try:
                own[k] = ProductConvolution(a["basis"], a["coefficients"], shape=shape,
                                            grid=(a["grid_y"], a["grid_x"]),
                                            metadata=meta.get(str(k), {}))
            except ValueError as exc:
                raise ValueError(f"{os.fspath(path)!r}: inconsistent family file: image "
                                 f"{k}'s own operator: {exc}") from exc
        family = cls(arr["basis"], arr["space"], (arr["grid_y"], arr["grid_x"]), shape,
                     arr["gammas"], Cone(arr["cone"]),
                     grid_step=float(header.get("grid_step", 32.0)),
                     metadata=header.get("metadata", {}), own=own, family_weights=weights)
        where = repr(os.fspath(path))
        for name, nodes in zip(("grid_y", "grid_x"), family.grid, strict=True):
            if nodes.ndim != 1 or nodes.size < 2 or not np.all(np.diff(nodes) > 0):
                raise ValueError(f"{where}: inconsistent family file: `{name}` must be "
                                 f"strictly increasing node positions, got {nodes}")
        # the cone's generators are PSFs in the basis: each a blur of bounded light (a
        # damaged cone would make every projection onto it fail)
        flat = family.basis.reshape(family.n_psf, -1)
        gens = np.asarray(arr["cone"], dtype=np.float64)
        sums = gens @ flat.sum(axis=1)
        l1 = np.abs(gens) @ np.abs(flat).sum(axis=1)
        bad = np.flatnonzero(~((sums > 0) & (l1 <= MAX_PSF_L1)))
        if bad.size:
            raise ValueError(f"{where}: inconsistent family file: the cone's generator "
                             f"{bad[0]} sums to {sums[bad[0]]:.3g} ({l1[bad[0]]:.3g} in "
                             f"absolute value), expected a PSF: a positive sum, at most "
                             f"{MAX_PSF_L1:g} in absolute value")
        # the family's own maps, before any projection (identification reads them) and
        # each learnt image's operator: blurs over the field
        for k in range(family.n_images):
            check_model_field(family.basis, family.maps(family.gammas[k]), shape,
                              *family.grid, f"{where} (image {k} in the family's maps)")
            op = family.operator(k)
            grid = op.grid if op.grid is not None else (np.arange(shape[0]),
                                                        np.arange(shape[1]))
            check_model_field(op.basis, op.coefficients, shape, *grid,
                              f"{where} (image {k}'s operator)")
        return family


def save_family(subspace: OperatorFamily, path) -> None:
    """Write ``subspace`` to ``path``: :meth:`OperatorFamily.save`."""
    subspace.save(path)


def load_family(path) -> OperatorFamily:
    """Read a subspace written by :func:`save_family`: :meth:`OperatorFamily.load`."""
    return OperatorFamily.load(path)


def __getattr__(name: str):
    """Old names of this module's family (deprecated)."""
    from ..common.deprecate import module_getattr

    return module_getattr(__name__, {
        "OperatorSubspace": ("OperatorFamily", lambda: OperatorFamily),
        "load_subspace": ("load_family", lambda: load_family),
        "save_subspace": ("save_family", lambda: save_family)})(name)
