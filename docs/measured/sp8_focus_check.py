"""Cross-check of the SP8 diagnosis with the z-stack: is the "illumination" found on the
in-focus slice a throughput over the field, or each bead's distance to focus?

    python docs/measured/sp8_focus_check.py      (from the repository root, ../shared beside it)

For the beads the diagnosis judges, it measures each bead's flux (11 x 11 box minus the
local median) in every slice, the slice where it peaks, and compares them with the
throughput the diagnosis fitted (coefficients from docs/measured/sp8_confocal_beads/report.json).
"""

import json
from pathlib import Path

import numpy as np
import tifffile
from scipy import stats

from napari_psfspace.core.beads.detect import KEPT
from napari_psfspace.core.diagnosis.loop import prepare_beads
from napari_psfspace.core.diagnosis.photometry import throughput_at

root = Path(__file__).resolve().parents[2]
stack = tifffile.imread(root.parent / "shared/data/sp8_confocal_beads/"
                        "sp8_series045_beads_zyx_uint8.tif").astype(float)
img = stack[32]
r = 0.5 / 0.04435
beads = prepare_beads(img, r)
pos = beads.positions[beads.status == KEPT]
report = json.loads((root / "docs/measured/sp8_confocal_beads/report.json").read_text())
ill = next(s for s in report["steps"] if s["effect"] == "illumination")["params"]["coefficients"]
t = throughput_at(ill, pos, img.shape)
iy, ix = np.round(pos).astype(int).T
h = 5
flux = np.array([[stack[z, y - h:y + h + 1, x - h:x + h + 1].sum()
                  - (2 * h + 1) ** 2 * np.median(stack[z, y - 3 * h:y + 3 * h, x - 3 * h:x + 3 * h])
                  for z in range(stack.shape[0])] for y, x in zip(iy, ix, strict=True)])  # (K, Z)
zbest = flux.argmax(1)
fmax = flux.max(1)
f32 = flux[:, 32]
print(f"{len(pos)} beads; slice of best focus 5/50/95 %: {np.percentile(zbest, [5, 50, 95])}")
# tilt of best-focus z over the field
X = np.column_stack([np.ones(len(pos)), pos[:, 0], pos[:, 1]])
b, *_ = np.linalg.lstsq(X, zbest, rcond=None)
print(f"best-focus plane: dz/drow {b[1]:.4f}, dz/dcol {b[2]:.4f} slices/px "
      f"({b[1] * 1024:.1f} and {b[2] * 1024:.1f} slices over the field)")
rho = {name: stats.spearmanr(t, v).statistic for name, v in
       [("flux in slice 32", f32), ("flux at best focus", fmax),
        ("slice of best focus", zbest), ("flux 32 / flux at best focus", f32 / fmax)]}
for name, v in rho.items():
    print(f"Spearman(throughput, {name}) = {v:.2f}")
