"""Headless core of napari-psfspace.

Pure numpy / scipy / scikit-image. This package must never import napari, Qt or
magicgui (``tests/test_layering.py`` enforces it).
"""
