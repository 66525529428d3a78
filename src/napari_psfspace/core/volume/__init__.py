"""Stage 6, volume: space-varying 3D PSFs from bead z-stacks.

A z-stack of beads on a coverslip gives, at every bead, the 3D PSF of a point on one
plane. :func:`~.estimate3d.estimate_operator_3d` learns a small basis of 3D kernels and
their lateral maps (the 2D method's PCA, thin-plate field and cone, on 3D patches
referenced to the common bead plane); the result is a
:class:`~.operator3d.ProductConvolution3D` with 3D FFT ``apply`` / ``adjoint`` and the
model family's pickle-free file format. Imports ``model``, ``beads`` and ``common``.
"""

from .estimate3d import Estimation3D, estimate_operator_3d, iter_estimate_operator_3d
from .operator3d import ProductConvolution3D, load_operator_3d

__all__ = ["Estimation3D", "ProductConvolution3D", "estimate_operator_3d",
           "iter_estimate_operator_3d", "load_operator_3d"]
