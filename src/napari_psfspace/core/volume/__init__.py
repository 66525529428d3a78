"""Stage 6, volume: space-varying 3D PSFs from bead z-stacks.

A z-stack of beads on a coverslip gives, at every bead, the 3D PSF of a point on one
plane. :func:`~.estimate3d.estimate_operator_3d` learns a small basis of 3D kernels and
their lateral maps (the 2D method's PCA, thin-plate field and cone, on 3D patches
referenced to the common bead plane); the result is a
:class:`~.operator3d.ProductConvolution3D` with 3D FFT ``apply`` / ``adjoint`` and the
model family's pickle-free file format. Deblurring: Richardson-Lucy and sparse + smooth
on lateral blocks (``blocks3d``), and on tiles through dask: tiles that exchange their
margins every iteration, the whole volume's result (``exchange3d``), or independent
tiles (``tiles3d``). Imports
``model``, ``beads``, ``diagnosis``, ``restore`` and ``common``.
"""

from .deconvolve3d import iter_richardson_lucy_3d, richardson_lucy_3d, shift_invariant
from .estimate3d import Estimation3D, estimate_operator_3d, iter_estimate_operator_3d
from .exchange3d import iter_richardson_lucy_3d_exchange, richardson_lucy_3d_exchange
from .fista3d import deblur_3d, iter_deblur_3d
from .operator3d import ProductConvolution3D, load_operator_3d
from .tiles3d import richardson_lucy_3d_tiled

__all__ = ["Estimation3D", "ProductConvolution3D", "deblur_3d", "estimate_operator_3d",
           "iter_deblur_3d", "iter_estimate_operator_3d", "iter_richardson_lucy_3d",
           "iter_richardson_lucy_3d_exchange", "load_operator_3d", "richardson_lucy_3d",
           "richardson_lucy_3d_exchange", "richardson_lucy_3d_tiled", "shift_invariant"]
