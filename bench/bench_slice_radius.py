"""The suggested PSF radius slice by slice: a slice alone, and with its neighbours.

    python bench/run.py slice_radius

On every slice of the measured stacks (``../shared/data``: the SP8 confocal stack, the
astigmatic stack, the three single-bead stacks), ``suggest_slice_radius``: the slice's
own reading and the radius used (the median of the slice and its neighbours), and
whether it gave a reason. A table a stack: its slices, the neighbouring pairs whose own
readings differ by more than 1.5x, the pairs whose radii used do, and of those the pairs
where neither slice says why (the rule: none).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from benchlib import table
from napari_psfspace.core.beads.focus import SLICE_RATIO
from napari_psfspace.core.beads.slice_radius import suggest_slice_radius
from napari_psfspace.core.common.errors import PsfSpaceError
from napari_psfspace.io import read_stack

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
STACKS = ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif",
          "astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif",
          "single_bead_psfs/Bead_Image1_crop.tif",
          "single_bead_psfs/BIL113_zstack_z300nm_current.tif",
          "single_bead_psfs/pycudadecon_psf.tif")


def jumps(values: list[float]) -> list[int]:
    """The pairs (by their first slice) whose values differ by more than SLICE_RATIO."""
    out = []
    for k in range(len(values) - 1):
        a, b = values[k], values[k + 1]
        if np.isfinite(a) and np.isfinite(b) and max(a / b, b / a) > SLICE_RATIO:
            out.append(k)
    return out


def main() -> None:
    rows = []
    for rel in STACKS:
        path = DATA / rel
        if not path.exists():
            print(f"{rel}: absent, left out")
            continue
        stack = read_stack(path)[0]
        own, used, said = [], [], []
        for z in range(stack.shape[0]):
            try:
                found = suggest_slice_radius(stack, z)
                own.append(found.own)
                used.append(found.radius)
                said.append(bool(found.reason))
            except PsfSpaceError:
                own.append(np.nan)
                used.append(np.nan)
                said.append(True)  # the error says why
        unexplained = [k for k in jumps(used) if not (said[k] or said[k + 1])]
        rows.append({"stack": Path(rel).stem[:28], "slices": stack.shape[0],
                     "own_jumps": len(jumps(own)), "used_jumps": len(jumps(used)),
                     "unexplained": len(unexplained),
                     "reasons": int(sum(said)),
                     "largest_used_ratio": max((max(used[k] / used[k + 1],
                                                    used[k + 1] / used[k])
                                                for k in range(len(used) - 1)
                                                if np.isfinite(used[k])
                                                and np.isfinite(used[k + 1])), default=1.0)})
        print(rows[-1], file=sys.stderr, flush=True)
    print(table(rows, [("stack", "s"), ("slices", "d"), ("own_jumps", "d"),
                       ("used_jumps", "d"), ("unexplained", "d"), ("reasons", "d"),
                       ("largest_used_ratio", ".2f")]))


if __name__ == "__main__":
    main()
