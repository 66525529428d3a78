"""A family learnt from the slices of measured z-stacks, against each slice alone (issue 11).

    python bench/bench_subspace_measured.py [--data ../shared/data]

Each slice of a z-stack is the field at another focus. ``estimate_family`` learns one
family from a range of slices around focus, holding about a fifth of each slice's beads
out (spread over the field), and judges each slice's operator on them;
``estimate_operator`` on the slice alone holds out its own fifth (the same detection,
centring and split rule, so nearly always the same beads). Figure: the held-out residual
(relative l2 of the raw patch, amplitude fitted), mean over the slice's held-out beads,
and its noise floor. About 2 min.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchlib import table
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.io import read_image

SETS = {
    # name: (file under the data folder, first slice, last slice + 1, PSF radius in px)
    "sp8_confocal": ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", 26, 39, None),
    "astigmatic": ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", 27, 39, 10.0),
}


def run(name: str, data: Path) -> list[dict]:
    rel, a, b, r = SETS[name]
    path = data / rel
    slices = [read_image(path, index=z)[0] for z in range(a, b)]
    if r is None:  # 0.5 um at the file's pixel size
        r = 0.5 / read_image(path, index=a)[1].pixel_size
    t0 = time.perf_counter()
    sub = estimate_family(slices, psf_radius=r, holdout=0.2)
    seconds = time.perf_counter() - t0
    rows = []
    for k, z in enumerate(sub.metadata["images"]):
        fam = sub.metadata["heldout"][k]
        alone = estimate_operator(slices[z], psf_radius=r, holdout=0.2).metadata["heldout"]
        rows.append({
            "set": name, "slice": a + z, "beads": sub.metadata["beads_per_image"][k],
            "held": fam.get("n_beads", 0), "family": fam.get("residual_mean", np.nan),
            "alone": (alone or {}).get("residual_mean", np.nan),
            "held_alone": (alone or {}).get("n_beads", 0),
            "floor": fam.get("noise_floor_mean", np.nan),
            "I": sub.n_psf, "J": sub.n_space, "seconds": seconds})
        rows[-1]["change_%"] = 100 * (rows[-1]["family"] / rows[-1]["alone"] - 1)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path,
                    default=Path(__file__).resolve().parents[2] / "shared" / "data")
    args = ap.parse_args()
    rows = []
    for name in SETS:
        rows += run(name, args.data)
        print(f"  {name}: {rows[-1]['seconds']:.1f} s for the family", flush=True)
    cols = [("set", "s"), ("slice", "d"), ("beads", "d"), ("held", "d"), ("held_alone", "d"),
            ("I", "d"), ("J", "d"), ("family", ".4f"), ("alone", ".4f"), ("change_%", "+.1f"),
            ("floor", ".4f")]
    print("\nHeld-out residual of each slice's operator: from the family, and alone")
    print(table(rows, cols))


if __name__ == "__main__":
    main()
