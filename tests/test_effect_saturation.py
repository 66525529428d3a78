"""Saturation: clipped pixels masked in the fits and filled from a model for learning."""

import numpy as np

from napari_psfspace import simulate_beads
from napari_psfspace.core.diagnosis.loop import diagnose


def test_saturation_is_found_and_lowers_the_error_to_the_unsaturated_level():
    image, truth = simulate_beads((640, 640), 70, aberrations="moderate", seed=0,
                                  effects={"saturation": 3000})
    assert truth.effects["saturated_pixels"] > 300  # most bright beads clip
    d = diagnose(image, psf_radius=truth.psf_radius,
                 effects=["saturation", "basis_size", "field_smoothing"])
    assert "saturation" in d.added
    step = next(s for s in d.steps if s.effect == "saturation")
    assert step.params["level"] == 3000
    assert step.params["filled_beads"] >= 10
    # measured: 0.0233 -> 0.0132; the same field without clipping: 0.0132
    assert step.error_after < 0.7 * step.error_before
    clean, t = simulate_beads((640, 640), 70, aberrations="moderate", seed=0)
    base = diagnose(clean, psf_radius=t.psf_radius, effects=[])
    assert step.error_after < 1.15 * base.error_before
    # the model never sees a clipped value: filled pixels are at or above the level
    ctx = d.context
    clipped = image >= 3000
    assert ctx.pixel_mask[clipped].all()
    assert np.all(ctx.image[clipped] >= 3000)
