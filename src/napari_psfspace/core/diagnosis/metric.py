"""The one figure of a model's accuracy: the held-out error, defined once.

Every place that reports how well a model explains its beads (the Model and Diagnose
steps of the napari panel, ``psfspace estimate`` and ``psfspace diagnose``, the report
and ``report.json``) reports this quantity, computed by one function
(:func:`~napari_psfspace.core.diagnosis.loop.iter_heldout_error`, the baseline of the
diagnosis), under this name, with this definition and unit, and the same one-line
verdict against the noise floor.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

#: The metric's name, as every report prints it.
NAME = "held-out error"
#: Its definition.
DEFINITION = ("each bead's relative residual energy |data - model|^2 / |model|^2 over its "
              "patch, the model learnt without that bead (5-fold cross-fit over the beads), "
              "averaged over the beads")
#: Its unit.
UNIT = "fraction of the bead's energy"
#: Noise floor: the same average for a perfect model (the noise alone).
FLOOR_DEFINITION = ("the same average for a perfect model: what the noise alone leaves after "
                    "the same fit of amplitude and background")
#: Within this factor of the noise floor the model explains the beads to the noise.
AT_FLOOR = 1.5


@dataclass(frozen=True)
class HeldoutError:
    """The held-out error of a model on an image's beads.

    Attributes
    ----------
    error : float
        :data:`NAME` (:data:`DEFINITION`), in :data:`UNIT`.
    noise_floor : float
        :data:`FLOOR_DEFINITION`.
    chi2_dof : float
        The beads' mean chi-square per degree of freedom under the noise model.
    n_beads : int
        The beads the means are over.
    noise_source : str
        Where the noise model came from (camera values, photon transfer, a fallback).
    """

    error: float
    noise_floor: float
    chi2_dof: float
    n_beads: int
    noise_source: str = ""

    def line(self) -> str:
        """``held-out error E (noise floor F, N beads): verdict``."""
        return line(self.error, self.noise_floor, self.n_beads)

    def to_dict(self) -> dict:
        """JSON-ready (a figure that could not be measured is None, never NaN)."""
        out = {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
               for k, v in asdict(self).items()}
        return {**out, "name": NAME, "definition": DEFINITION, "unit": UNIT}


def verdict(error: float, noise_floor: float) -> str:
    """One line against the noise floor."""
    if not (np.isfinite(error) and np.isfinite(noise_floor) and noise_floor > 0):
        return "no noise floor to judge it against"
    ratio = error / noise_floor
    if ratio <= AT_FLOOR:
        return f"{ratio:.1f}x the noise floor: the model explains the beads to their noise"
    return (f"{ratio:.1f}x the noise floor: the beads show structure the model lacks "
            "(Diagnose traces it)")


def line(error: float, noise_floor: float, n_beads: int) -> str:
    """``held-out error E (noise floor F, N beads): verdict``: how every report says it."""
    return (f"{NAME} {error:.4g} (noise floor {noise_floor:.4g}, {int(n_beads)} beads): "
            f"{verdict(error, noise_floor)}")
