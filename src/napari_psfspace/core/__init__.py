"""Headless core of napari-psfspace, one folder per stage of the method.

Data flow one way, from the image to the restored sample::

    beads  ->  model  ->  diagnosis
                     \\->  family    ->  restore

- :mod:`~napari_psfspace.core.beads`: find isolated beads in an image, centre them
  sub-pixel, cut windowed patches and remove their background.
- :mod:`~napari_psfspace.core.model`: learn one space-varying operator from the patches
  (PCA basis, thin-plate field, cone, held-out choice, noise-aware refit, motion test)
  and the product-convolution operator itself with its file format.
- :mod:`~napari_psfspace.core.diagnosis`: judge a model by honest residuals (noise model,
  cross-fitting, residual tests) and close the loop with effects the model lacks.
- :mod:`~napari_psfspace.core.family` and
  :mod:`~napari_psfspace.core.restore`: a family of operators from many
  images, and blind deblurring with it.
- :mod:`~napari_psfspace.core.simulation`: the bead-image simulator with its known truth
  and the scene set, for tests and benches (beside the flow: nothing in it is needed
  to process a measured image, and no stage imports it).
- :mod:`~napari_psfspace.core.common`: plumbing every stage may use (atomic writes,
  threads, input checks, mosaics).

A stage imports only from itself, from stages before it and from ``common``
(``tests/test_layering.py`` checks every import). Pure numpy / scipy / scikit-image:
this package never imports napari, Qt or magicgui.
"""
