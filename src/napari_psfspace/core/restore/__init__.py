"""Stage 5, restore: blind deblurring with a family of operators.

Takes an image of a sample with a few beads and a family of stage 4: identifies the
operator of the family that explains the beads (:mod:`.identify`: in the family's own few
dimensions, each clicked bead judged by the others, :mod:`.bead_check`; or problem (9) of
the paper, :mod:`.cone_identify`) and solves a sparse + smooth deconvolution with it
(:mod:`.deconvolve`, by the block FISTA of :mod:`.fista`). Imports ``family``, ``model``,
``beads``, ``common`` and the noise model of ``diagnosis``.
"""

from .deconvolve import Deblurred, deblur, iter_deblur
from .identify import identify_operator

__all__ = ["Deblurred", "deblur", "identify_operator", "iter_deblur"]
