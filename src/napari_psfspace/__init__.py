"""napari-psfspace: learn space-varying PSF operators from micro-bead images."""

__version__ = "0.1.0"
