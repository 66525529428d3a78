"""The blur operators as linear operators to the solvers that take one.

:class:`ImageOperator` makes an operator on images (``apply`` and ``adjoint`` on arrays of
``image_shape``) a :class:`scipy.sparse.linalg.LinearOperator` on the flattened images,
as pylops does with its ``dims``: ``shape`` is ``(N, N)`` with ``N`` the number of
pixels (or voxels), ``dtype`` is float64, and ``@``, ``.H``, ``matvec`` and ``rmatvec``
work as scipy's solvers (``lsqr``, ``cg``, ``gmres``) expect. ``op @ u`` and
``op.H @ v`` also take an image of ``image_shape`` itself and return one; a flat vector
in gives a flat vector out. :meth:`ImageOperator.to_pylops` hands the same operator to
pylops (and so to pyproximal), with ``dims`` and ``dimsd`` set to the image's shape.

The operators are real, so the adjoint is the transpose.
"""

from __future__ import annotations

from math import prod

import numpy as np
from scipy.sparse.linalg import LinearOperator

__all__ = ["ImageOperator"]


class ImageOperator(LinearOperator):
    """A real linear operator on images, seen by scipy as one on flattened vectors.

    Subclasses define ``image_shape`` (the shape the operator acts on) and
    ``apply(u)`` and ``adjoint(v)`` on arrays of that shape; ``adjoint()`` without an
    argument is the adjoint operator, as in scipy and pylops.
    """

    @property
    def image_shape(self) -> tuple[int, ...]:  # pragma: no cover - every subclass sets it
        raise NotImplementedError

    @property
    def shape(self) -> tuple[int, int]:
        """``(N, N)``, ``N`` the number of pixels (voxels) of ``image_shape``: the
        operator on row-major flattened images."""
        n = prod(self.image_shape)
        return (n, n)

    @property
    def dtype(self) -> np.dtype:
        """float64: a flat vector in float64 comes out in float64 (float32 in gives
        float32 out)."""
        return np.dtype(np.float64)

    def _is_image(self, x) -> bool:
        """``x`` is an image the operator acts on (not a flattened vector or block)."""
        shape = tuple(getattr(x, "shape", ()))
        return shape == tuple(self.image_shape)

    # scipy's hooks: flattened vectors (N,) or (N, 1) in, the same out
    def _matvec(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.apply(np.reshape(x, self.image_shape))).reshape(x.shape)

    def _rmatvec(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.adjoint(np.reshape(x, self.image_shape))).reshape(x.shape)

    def _adjoint(self) -> LinearOperator:
        return _Adjoint(self)

    _transpose = _adjoint

    def dot(self, x):
        """``H x``: an image of ``image_shape`` gives an image, a flat vector a flat
        vector, a LinearOperator a product operator (scipy's rules)."""
        if self._is_image(x):
            return self.apply(x)
        return super().dot(x)

    def __matmul__(self, x):
        if np.isscalar(x):
            raise ValueError("Scalar operands are not allowed, use '*' instead")
        return self.dot(x)

    def to_pylops(self):
        """The operator as a :class:`pylops.LinearOperator` with ``dims`` and ``dimsd``
        the image's shape (pylops' solvers and pyproximal take it as it is).

        Raises
        ------
        ImportError
            Where pylops is not installed (``pip install pylops``).
        """
        try:
            import pylops
        except ImportError as exc:  # an optional dependency
            raise ImportError("`to_pylops` needs pylops: pip install pylops") from exc
        return pylops.LinearOperator(Op=self, dims=tuple(self.image_shape),
                                     dimsd=tuple(self.image_shape), explicit=False)


class _Adjoint(ImageOperator):
    """The adjoint of an :class:`ImageOperator`: ``apply`` is its ``adjoint``."""

    def __init__(self, op: ImageOperator) -> None:
        self._op = op

    @property
    def image_shape(self) -> tuple[int, ...]:
        return tuple(self._op.image_shape)

    def _is_image(self, x) -> bool:
        return self._op._is_image(x)

    def apply(self, v, **kwargs):
        return self._op.adjoint(v, **kwargs)

    def adjoint(self, u=None, **kwargs):
        if u is None:
            return self._op
        return self._op.apply(u, **kwargs)

    def _adjoint(self) -> LinearOperator:
        return self._op

    _transpose = _adjoint

    def __repr__(self) -> str:
        return f"{self._op!r}.H"
