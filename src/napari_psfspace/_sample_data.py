"""Sample data for napari: a simulated bead field with its ground truth.

Generated on the fly (about a second); returns napari layer-data tuples without
importing napari.
"""

from __future__ import annotations

from .core.simulation import simulate_beads


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
        (image, {"name": "simulated beads", "scale": (px, px),
                 "metadata": meta}, "image"),
        (truth.positions, {"name": "true bead centres", "scale": (px, px), "size": 6,
                           "face_color": "transparent", "border_color": "yellow",
                           "visible": False}, "points"),
    ]
