"""Aberrations that vary over the field: Zernike coefficients as low-degree polynomials
of the field position (:class:`FieldAberrations`), with named presets and random fields.

Units: waves rms; the field position ``(u, v)`` runs over [-1, 1] across the image.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

#: Monomials of the field polynomials, in the order of ``FieldAberrations.terms``.
FIELD_BASIS = ("1", "u", "v", "u^2", "u*v", "v^2")


def _field_uv(y, x, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Normalised field coordinates ``u`` (columns) and ``v`` (rows) in [-1, 1]."""
    half_h = max((shape[0] - 1) / 2.0, 0.5)
    half_w = max((shape[1] - 1) / 2.0, 0.5)
    u = (np.asarray(x, float) - (shape[1] - 1) / 2.0) / half_w
    v = (np.asarray(y, float) - (shape[0] - 1) / 2.0) / half_h
    return u, v


def _field_basis(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Monomials ``(1, u, v, u^2, u v, v^2)`` stacked on a new last axis."""
    u, v = np.broadcast_arrays(u, v)
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1)


@dataclass(frozen=True)
class FieldAberrations:
    """Zernike coefficients as smooth low-degree polynomials of the field position.

    Coefficients are in waves rms (Noll normalisation). The field coordinates
    ``(u, v)`` are normalised to ``[-1, 1]``: ``u`` along columns (x), ``v``
    along rows (y), ``(0, 0)`` at the field centre, ``±1`` at the centres of
    the border pixels.

    Parameters
    ----------
    terms : Mapping[int, tuple of float]
        Noll index ``j`` -> polynomial coefficients in the basis
        ``(1, u, v, u^2, u*v, v^2)``; shorter tuples are zero padded.
    """

    terms: Mapping[int, tuple[float, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        clean: dict[int, tuple[float, ...]] = {}
        for j, coefs in dict(self.terms).items():
            if int(j) < 1:
                raise ValueError(f"Noll index must be >= 1, got {j}")
            coefs = tuple(float(c) for c in np.atleast_1d(coefs))
            if len(coefs) > len(FIELD_BASIS):
                raise ValueError(
                    f"term {j}: at most {len(FIELD_BASIS)} coefficients {FIELD_BASIS}, "
                    f"got {len(coefs)}"
                )
            clean[int(j)] = coefs + (0.0,) * (len(FIELD_BASIS) - len(coefs))
        object.__setattr__(self, "terms", dict(sorted(clean.items())))

    def __hash__(self) -> int:
        return hash(tuple(self.terms.items()))

    @property
    def noll_indices(self) -> tuple[int, ...]:
        """Noll indices with a (possibly zero) polynomial, increasing."""
        return tuple(self.terms)

    def coefficient_matrix(self, y, x, shape: tuple[int, int]) -> np.ndarray:
        """Zernike coefficients at many field positions.

        Parameters
        ----------
        y, x : array_like
            Row and column positions in pixels, broadcastable shapes ``S``.
        shape : tuple of int
            ``(H, W)`` of the image the positions refer to.

        Returns
        -------
        ndarray, shape ``S + (len(noll_indices),)``
            Coefficients in waves rms, columns ordered as :attr:`noll_indices`.
        """
        basis = _field_basis(*_field_uv(y, x, shape))
        poly = np.array([self.terms[j] for j in self.noll_indices], float).reshape(-1, 6)
        return basis @ poly.T

    def coefficients(self, y: float, x: float, shape: tuple[int, int]) -> dict[int, float]:
        """Zernike coefficients ``{noll j: waves rms}`` at pixel ``(y, x)`` of image ``shape``."""
        values = self.coefficient_matrix(float(y), float(x), shape)
        return {j: float(c) for j, c in zip(self.noll_indices, values, strict=True)}

    @classmethod
    def preset(cls, name: str) -> FieldAberrations:
        """Named aberration field.

        Parameters
        ----------
        name : {"none", "moderate", "strong"}
            ``"moderate"``: defocus from a tilted coverslip, astigmatism
            growing as the squared field radius, field-linear coma, a little
            spherical aberration. ``"strong"``: tilted and curved coverslip
            (defocus with a quadratic term), stronger astigmatism and coma.

        Returns
        -------
        FieldAberrations
        """
        try:
            return cls(PRESETS[name])
        except KeyError:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}") from None

    @classmethod
    def random(
        cls,
        strength: float,
        seed: int | np.random.Generator | None = None,
        noll: Sequence[int] = (4, 5, 6, 7, 8, 11),
    ) -> FieldAberrations:
        """Random low-degree (<= 2) polynomial aberration field.

        Each coefficient of each polynomial is drawn from a centred normal law
        with standard deviation ``strength / sqrt(6)``, so that the rms of each
        Zernike coefficient over the field is of the order of ``strength``.

        Parameters
        ----------
        strength : float
            Typical rms (over the field) of each Zernike coefficient, waves rms.
        seed : int, Generator or None
            Seed of :func:`numpy.random.default_rng`.
        noll : sequence of int
            Noll indices that receive a random polynomial.

        Returns
        -------
        FieldAberrations
        """
        if strength < 0:
            raise ValueError(f"strength must be >= 0, got {strength}")
        rng = np.random.default_rng(seed)
        scale = strength / np.sqrt(len(FIELD_BASIS))
        return cls({j: tuple(rng.normal(0.0, scale, len(FIELD_BASIS))) for j in noll})


#               1      u      v      u^2    u*v    v^2
PRESETS: dict[str, dict[int, tuple[float, ...]]] = {
    "none": {},
    "moderate": {
        4: (0.0, 0.075, 0.05, 0.0, 0.0, 0.0),
        5: (0.0, 0.0, 0.0, 0.0, 0.12, 0.0),
        6: (0.0, 0.0, 0.0, 0.06, 0.0, -0.06),
        7: (0.0, 0.0, 0.03, 0.0, 0.0, 0.0),
        8: (0.0, 0.03, 0.0, 0.0, 0.0, 0.0),
        11: (0.02, 0.0, 0.0, 0.0, 0.0, 0.0),
    },
    "strong": {
        4: (-0.04, 0.09, 0.06, 0.08, 0.0, 0.08),
        5: (0.0, 0.0, 0.0, 0.0, 0.22, 0.0),
        6: (0.0, 0.0, 0.0, 0.11, 0.0, -0.11),
        7: (0.0, 0.0, 0.04, 0.0, 0.0, 0.0),
        8: (0.0, 0.04, 0.0, 0.0, 0.0, 0.0),
        11: (0.03, 0.0, 0.0, 0.0, 0.0, 0.0),
    },
}


def as_aberrations(aberrations: str | FieldAberrations | None) -> FieldAberrations:
    if aberrations is None:
        return FieldAberrations()
    if isinstance(aberrations, str):
        return FieldAberrations.preset(aberrations)
    if isinstance(aberrations, FieldAberrations):
        return aberrations
    raise TypeError(
        f"aberrations must be a preset name, FieldAberrations or None, got {aberrations!r}"
    )
