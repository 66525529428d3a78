"""Regenerate the README figures: ``python docs/make_figures.py`` (about 30 s).

Runs the demo's default scene (2048x2048, 400 beads, strong aberrations, seed 0) in a
temporary folder and copies its PSF-grid and basis figures to docs/images/.
"""

import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from napari_psfspace.demo import format_table, run_demo  # noqa: E402

OUT = Path(__file__).resolve().parent / "images"

if __name__ == "__main__":
    OUT.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        result = run_demo(tmp, scene="wide", seed=0)
        for name in ["psf_grid.png", "basis.png", "coefficient_maps.png"]:
            shutil.copy(Path(tmp) / name, OUT / f"demo_{name}")
    print(format_table(result))
