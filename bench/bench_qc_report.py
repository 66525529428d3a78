"""The QC report on every measured z-stack: its time against ``estimate3d`` on the same
stack, its size, and what it says.

    python bench/run.py qc_report

Both commands run as a user runs them (``python -m napari_psfspace.cli``, one after the
other, the same PSF radius as ``fwhm_reference``); ``qc`` is given the optics where the
data's README or metadata state them (the SP8: NA 1.40, emission 580-695 nm, taken as
640 nm; the astigmatic stack: NA 0.85, 520 nm), else none (no theory, no verdict on
it). Columns: seconds of each, their ratio (the issue's bound: 1.5), the page's size
(bound: 5 MB for the 71 x 1024 x 1024 SP8 stack), the verdict, the centre's FWHM and the
number of warnings.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchlib import table

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
#: (path under ../shared/data, PSF radius px, NA, emission nm)
STACKS = (
    ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", 22, 1.4, 640.0),
    ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", 16, 0.85, 520.0),
    ("single_bead_psfs/Bead_Image1_crop.tif", 16, None, None),
    ("single_bead_psfs/BIL113_zstack_z300nm_current.tif", 16, None, None),
    ("single_bead_psfs/pycudadecon_psf.tif", 16, None, None),
)


def _run(args: list[str]) -> tuple[float, subprocess.CompletedProcess]:
    t0 = time.perf_counter()
    got = subprocess.run([sys.executable, "-m", "napari_psfspace.cli", *args],
                         capture_output=True, text=True)
    return time.perf_counter() - t0, got


def main() -> None:
    rows = []
    for rel, radius, na, wl in STACKS:
        path = DATA / rel
        if not path.exists():
            print(f"skipped {rel}: ../shared/data is not beside the repository")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            t_est, est = _run(["estimate3d", str(path), "-o", f"{tmp}/m.npz",
                               "--psf-radius", str(radius), "-q"])
            optics = ["--na", str(na), "--wavelength-nm", str(wl)] if na else []
            t_qc, qc = _run(["qc", str(path), "-o", f"{tmp}/qc", "--psf-radius",
                             str(radius), "-q", *optics])
            name = path.stem[:24]
            if qc.returncode != 0:
                print(f"{rel}: qc failed: {qc.stderr.strip()}")
                rows.append({"stack": name, "estimate_s": t_est, "qc_s": t_qc,
                             "verdict": "error"})
                continue
            rec = json.loads(Path(f"{tmp}/qc/qc.json").read_text(encoding="utf-8"))
            size = Path(f"{tmp}/qc/qc.html").stat().st_size / 1e6
        print(f"{rel}: estimate3d {t_est:.1f} s (rc {est.returncode}), qc {t_qc:.1f} s, "
              f"page {size:.2f} MB; warnings: {rec['warnings']}", flush=True)
        rows.append({"stack": name, "estimate_s": t_est, "qc_s": t_qc,
                     "ratio": t_qc / t_est, "page_MB": size,
                     "verdict": {True: "pass", False: "fail", None: "-"}[rec["passed"]],
                     "lateral_nm": rec["centre_fwhm_lateral_nm"],
                     "axial_nm": rec["centre_fwhm_axial_nm"],
                     "used": rec["beads"]["used"], "warnings": len(rec["warnings"])})
    print("\nThe QC report against estimate3d on the same stack (seconds, as a user runs "
          "them)")
    print(table(rows, [("stack", "s"), ("estimate_s", ".1f"), ("qc_s", ".1f"),
                       ("ratio", ".2f"), ("page_MB", ".2f"), ("verdict", "s"),
                       ("lateral_nm", ".0f"), ("axial_nm", ".0f"), ("used", "d"),
                       ("warnings", "d")]))


if __name__ == "__main__":
    main()
