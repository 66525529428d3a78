"""Model extensions ("effects") that :func:`~napari_psfspace.core.diagnosis.loop.diagnose` can add.

Each lives in its own module with the small interface of :class:`base.Effect`:
``evidence`` (from the residual analysis), ``fit`` and ``apply``.
"""

from .background_structure import BackgroundStructure
from .base import REGISTRY, Context, Effect
from .bead_size import BeadSize
from .fixed_pattern import FixedPattern
from .illumination import Illumination
from .model_size import BasisSize, FieldSmoothing
from .neighbours import Neighbours
from .nonlinearity import Nonlinearity
from .outliers import OutlierPixels
from .saturation import Saturation

__all__ = ["REGISTRY", "BackgroundStructure", "BasisSize", "BeadSize", "Context", "Effect",
           "FieldSmoothing", "FixedPattern", "Illumination", "Neighbours", "Nonlinearity",
           "OutlierPixels", "Saturation"]
