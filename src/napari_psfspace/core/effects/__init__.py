"""Model extensions ("effects") that :func:`~napari_psfspace.core.diagnose.diagnose` can add.

Each lives in its own module with the small interface of :class:`base.Effect`:
``evidence`` (from the residual analysis), ``fit`` and ``apply``.
"""

from .base import REGISTRY, Context, Effect
from .fixed_pattern import FixedPattern
from .model_size import BasisSize, FieldSmoothing
from .neighbours import Neighbours
from .outliers import OutlierPixels
from .saturation import Saturation

__all__ = ["REGISTRY", "BasisSize", "Context", "Effect", "FieldSmoothing", "FixedPattern",
           "Neighbours", "OutlierPixels", "Saturation"]
