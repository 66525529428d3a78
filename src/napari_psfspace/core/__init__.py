"""Headless core of napari-psfspace, one folder per stage of the method.

Data flow one way, from the image to the restored sample::

    beads  ->  model  ->  diagnosis
                     \\->  subspace  ->  restore

- :mod:`~napari_psfspace.core.beads`: find isolated beads in an image, centre them
  sub-pixel, cut windowed patches and remove their background.
- :mod:`~napari_psfspace.core.model`: learn one space-varying operator from the patches
  (PCA basis, thin-plate field, cone, held-out choice, noise-aware refit, motion test)
  and the product-convolution operator itself with its file format.
- :mod:`~napari_psfspace.core.diagnosis`: judge a model by honest residuals (noise model,
  cross-fitting, residual tests) and close the loop with effects the model lacks.
- :mod:`~napari_psfspace.core.subspace` (issue 11) and
  :mod:`~napari_psfspace.core.restore` (issue 12): a family of operators from many
  images, and blind deblurring with it.
- :mod:`~napari_psfspace.core.simulation`: the bead-image simulator with its known truth
  and the scene family, for tests and benches (beside the flow: nothing in it is needed
  to process a measured image, and no stage imports it).
- :mod:`~napari_psfspace.core.common`: plumbing every stage may use (atomic writes,
  threads, input checks, mosaics).

A stage imports only from itself, from stages before it and from ``common``
(``tests/test_layering.py`` checks every import). Pure numpy / scipy / scikit-image:
this package never imports napari, Qt or magicgui.

The flat module paths of earlier versions (``napari_psfspace.core.estimate``, ...) still
import, as the same module objects (:data:`MOVED`); new code uses the stage paths.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys

#: Flat module paths before the stage folders (issue 10) -> where each module lives now.
MOVED: dict[str, str] = {
    "_atomic": "common.atomic", "_threads": "common.threads", "_validate": "common.validate",
    "mosaic": "common.mosaic",
    "detect": "beads.detect", "centering": "beads.centering", "spikes": "beads.spikes",
    "background": "beads.background", "window": "beads.window", "patches": "beads.patches",
    "sphere": "beads.sphere",
    "pca": "model.pca", "tps": "model.tps", "field": "model.field", "voronoi": "model.voronoi",
    "cone": "model.cone", "operator": "model.operator", "estimate": "model.estimate",
    "heldout": "model.heldout", "fewbeads": "model.fewbeads", "denoise": "model.denoise",
    "motion": "model.motion", "review": "model.review",
    "noise": "diagnosis.noise", "residuals": "diagnosis.residuals",
    "crossfit": "diagnosis.crossfit", "photometry": "diagnosis.photometry",
    "analysis": "diagnosis.analysis", "diagnose": "diagnosis.loop",
    "effects": "diagnosis.effects",
    "zernike": "simulation.zernike", "simulate": "simulation",
    "scenes": "simulation.family", "metrics": "simulation.metrics",
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Import an old flat path as the module (the same object) at its stage path."""

    prefix = __name__ + "."

    def _target(self, fullname: str) -> str | None:
        if not fullname.startswith(self.prefix):
            return None
        head, _, tail = fullname[len(self.prefix):].partition(".")
        if head not in MOVED:
            return None
        return self.prefix + MOVED[head] + ("." + tail if tail else "")

    def find_spec(self, fullname, path=None, target=None):
        new = self._target(fullname)
        if new is None:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        return importlib.import_module(self._target(spec.name))

    def exec_module(self, module):
        pass  # the module at its stage path is already executed


if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.insert(0, _MovedModules())
