"""``report.json``: the diagnosis as data (``docs/report-format.md``), strict JSON.
"""

from __future__ import annotations

import math
import os
from datetime import datetime, timezone
from typing import Any

import numpy as np

from ..core.common.measures import field_fwhm, in_units
from ..core.common.version import package_version
from .figures import FIGURES
from .markdown import effect_descriptions

#: ``format`` and ``version`` of report.json (docs/report-format.md).
REPORT_FORMAT = "napari-psfspace/diagnosis-report"

REPORT_VERSION = 1

# ------------------------------------------------------------------ JSON
def to_jsonable(obj: Any) -> Any:
    """A copy with numpy types as Python ones, tuples as lists, NaN / inf as None."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj

def _fwhm_dict(op, pixel_size: float | None) -> dict:
    """The model's lateral FWHM at the centre and the corners (Gaussian fits with an
    offset), pixels and, where the pixel size is known, nm."""
    out = {}
    for place, m in field_fwhm(op).items():
        row = {k: m[k] for k in ("row", "col", "fwhm_lateral", "fwhm_row", "fwhm_col",
                                 "fwhm_major", "fwhm_minor", "ellipticity", "angle")}
        if pixel_size:
            nm, _ = in_units(m, (pixel_size, pixel_size))
            row.update({f"{k}_nm": nm[k] for k in ("fwhm_lateral", "fwhm_row", "fwhm_col",
                                                   "fwhm_major", "fwhm_minor")})
        out[place] = row
    return out

def report_dict(diagnosis, *, image_name: str = "image", pixel_size: float | None = None,
                extra: dict | None = None) -> dict:
    """The content of report.json (docs/report-format.md), JSON-safe."""
    d = diagnosis
    r = float(d.context.psf_radius)
    op = d.operator
    run = {"image": str(image_name), "image_shape": list(d.context.image.shape),
           "psf_radius_px": r, "psf_radius_um": r * pixel_size if pixel_size else None,
           "pixel_size_um": pixel_size, "software": "napari-psfspace",
           "version": package_version(),
           "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           **(extra or {})}
    out = {
        "format": REPORT_FORMAT, "version": REPORT_VERSION, "run": run,
        **d.to_dict(),
        "relative_drop": (1 - d.error_after / d.error_before) if d.error_before else None,
        "beads_before": d.crossfit_before.summary(),
        "beads_after": d.crossfit_after.summary(),
        "effects": effect_descriptions(d),
        "model": {"n_psf": int(op.n_psf), "psf_size": int(op.psf_size),
                  "shape": list(op.image_shape),
                  "n_beads_used": op.metadata.get("n_beads_used"),
                  "field_model": op.metadata.get("field_model"),
                  "field_model_reason": op.metadata.get("field_model_reason"),
                  "bead_correction": op.metadata.get("bead_correction"),
                  "denoise": op.metadata.get("denoise"),
                  "motion": op.metadata.get("motion"),
                  "fwhm": _fwhm_dict(op, pixel_size)},
        "figures": dict(FIGURES),
    }
    return to_jsonable(out)


__all__ = ["report_dict", "REPORT_FORMAT", "REPORT_VERSION", "to_jsonable"]
