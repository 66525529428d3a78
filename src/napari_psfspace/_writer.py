"""npe2 writers: the model file, and a PSF (or any image layer) as a calibrated TIFF.

* **Model (.npz)**: select the "PSF grid" layer (made by *Learn operator* or by opening a
  model file; its metadata holds the operator) and use File > Save Selected Layers with a
  ``.npz`` name. The file is written by ``ProductConvolution.save`` (atomic).
* **TIFF (.tif)**: an image layer, e.g. "PSF at position" from *Learn operator*, written
  by :func:`napari_psfspace.io.write_tiff` with its pixel size (``metadata["pixel_size_um"]``)
  and its position in the ImageJ Info field.
"""

from __future__ import annotations

import os


def write_model(path: str, data, attributes: dict) -> list[str]:
    """Save the operator held by an image layer's metadata as a model file.

    Raises
    ------
    ValueError
        The layer holds no model (the message says which layer to choose).
    """
    from ._layers import OPERATOR_KEY
    from .core.model.operator import ProductConvolution

    op = (attributes.get("metadata") or {}).get(OPERATOR_KEY)
    if not isinstance(op, ProductConvolution):
        raise ValueError(
            f"Layer {attributes.get('name')!r} holds no PSF model: select the 'PSF grid' "
            "layer made by 'Learn operator' (or opened from a model file) and save it as .npz."
        )
    op.save(path)
    return [os.fspath(path)]


def write_psf_tiff(path: str, data, attributes: dict) -> list[str]:
    """Write an image layer (e.g. the PSF at a position) as an ImageJ TIFF, atomically."""
    import numpy as np

    from .io import write_tiff

    meta = attributes.get("metadata") or {}
    info = {k: v for k, v in meta.items() if k in ("psf_row", "psf_column")}
    write_tiff(path, np.asarray(data), pixel_size=meta.get("pixel_size_um"),
               metadata=info or None)
    return [os.fspath(path)]
