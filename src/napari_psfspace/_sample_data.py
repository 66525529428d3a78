"""Sample data for napari: a simulated bead field with its ground truth.

Generated on the fly (about a second); returns napari layer-data tuples without
importing napari.
"""

from __future__ import annotations

from .core.simulation import simulate_beads

#: Focus of each slice of the focus-series sample relative to the bead plane, µm.
SERIES_Z_UM = (-0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6)


def simulated_beads(seed: int = 0):
    """A 768 x 768 bead image (moderate aberrations) and the true bead positions.

    Returns
    -------
    list of (data, kwargs, layer_type)
        The image (with its pixel size as scale, in micrometres) and a Points layer of
        the true bead centres.
    """
    image, truth = simulate_beads((768, 768), 90, aberrations="moderate", seed=seed)
    px = truth.optics.pixel_size
    meta = {"psf_radius": truth.psf_radius, "pixel_size_um": px, "simulated": True}
    return [
        (image, {"name": "simulated beads", "scale": (px, px), "units": ("µm", "µm"),
                 "metadata": meta}, "image"),
        (truth.positions, {"name": "true bead centres", "scale": (px, px),
                           "units": ("µm", "µm"), "size": 6,
                           "face_color": "transparent", "border_color": "yellow",
                           "visible": False}, "points"),
    ]


def simulated_focus_series(seed: int = 0):
    """A focus series of one bead field (7 slices of 512 x 512, -0.6 to 0.6 µm): the
    same microscope under seven conditions, for the Family step (a family of operators,
    one per slice).

    Returns
    -------
    list of (data, kwargs, layer_type)
        The stack (scale: z step and pixel size, µm; metadata: the widest slice's PSF
        radius in pixels, the pixel size and each slice's focus).
    """
    from .core.simulation.focus import simulate_focus_series

    stack, series = simulate_focus_series((512, 512), 40, SERIES_Z_UM, seed=seed)
    px = series.optics.pixel_size
    dz = float(SERIES_Z_UM[1] - SERIES_Z_UM[0])
    meta = {"psf_radius": int(series.psf_radius.max()), "pixel_size_um": px,
            "z_um": series.z_um.tolist(), "simulated": True}
    return [(stack, {"name": "simulated focus series", "scale": (dz, px, px),
                     "units": ("µm",) * 3, "metadata": meta}, "image")]
