"""Writes the OME-Zarr fixtures in ``tests/data/ome_zarr`` with the ecosystem's writer
(``ome-zarr``, not a dependency of this project: its pydantic pin clashes with
napari-psf-analysis), so that the reader is tested on files it did not write.

Run in an environment holding ``ome-zarr`` (0.18 was used)::

    python -m venv /tmp/oz && /tmp/oz/bin/pip install ome-zarr
    /tmp/oz/bin/python tests/data/make_ome_zarr_fixtures.py

Each image is ``np.arange`` in uint16, reshaped, so a reader's values are known too.
"""

import os
import shutil

import numpy as np
import zarr
from ome_zarr.format import FormatV04, FormatV05
from ome_zarr.io import parse_url
from ome_zarr.writer import write_image

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "ome_zarr")


def image(name, shape, axes, scale, fmt):
    path = os.path.join(HERE, name)
    shutil.rmtree(path, ignore_errors=True)
    data = np.arange(np.prod(shape), dtype=np.uint16).reshape(shape)
    store = parse_url(path, mode="w", fmt=fmt).store
    root = zarr.group(store=store, zarr_format=fmt.zarr_format)
    names = [a["name"] for a in axes]
    units = {a["name"]: a["unit"] for a in axes if "unit" in a}
    write_image(data, root, axes=axes, fmt=fmt, scale_factors=(2,),
                scale=dict(zip(names, scale, strict=True)), axes_units=units,
                storage_options={"chunks": tuple(min(s, 8) for s in shape)})


if __name__ == "__main__":
    zyx_um = [{"name": a, "type": "space", "unit": "micrometer"} for a in "zyx"]
    image("zyx_v04.zarr", (5, 12, 10), zyx_um, [0.3, 0.1, 0.1], FormatV04())
    image("zyx_v05.zarr", (5, 12, 10), zyx_um, [0.3, 0.1, 0.1], FormatV05())
    tczyx_nm = ([{"name": "t", "type": "time"}, {"name": "c", "type": "channel"}]
                + [{"name": a, "type": "space", "unit": "nanometer"} for a in "zyx"])
    image("tczyx_nm_v04.zarr", (1, 1, 4, 9, 11), tczyx_nm, [1.0, 1.0, 250.0, 65.0, 65.0],
          FormatV04())
