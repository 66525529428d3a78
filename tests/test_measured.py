"""The estimator on measured data: the in-focus slice of a Leica SP8 confocal bead stack.

Data: ../shared/data/sp8_confocal_beads (GitHub gerasimenkoab/simple_psf_extractor,
GPL-3.0); HC PL APO 100x/1.40 oil, pixel 44.35 nm, z step 100 nm.
"""

import numpy as np
import pytest

from napari_psfspace.core.estimate import iter_estimate, run_with_progress
from napari_psfspace.io import best_focus_index, read_image


def _fwhm(profile: np.ndarray) -> float:
    half = profile.max() / 2
    above = np.flatnonzero(profile >= half)
    i0, i1 = above[0], above[-1]
    left = i0 - 1 + (half - profile[i0 - 1]) / (profile[i0] - profile[i0 - 1])
    right = i1 + (profile[i1] - half) / (profile[i1] - profile[i1 + 1])
    return float(right - left)


@pytest.fixture(scope="module")
def sp8(shared_data):
    import tifffile

    path = shared_data / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif"
    z = best_focus_index(tifffile.imread(path))
    image, info = read_image(path, index=z)
    return z, image, info


def test_sp8_metadata_is_read(sp8):
    z, image, info = sp8
    assert image.shape == (1024, 1024) and image.dtype == np.uint8
    assert info.pixel_size == pytest.approx(0.04435, rel=1e-3)  # README: 44.35 nm
    assert info.z_spacing == pytest.approx(0.1)
    assert 28 <= z <= 36  # the brightest slices (maxima reach 255) are 30-35


def test_sp8_in_focus_slice(sp8):
    z, image, info = sp8
    r = 0.5 / info.pixel_size  # 0.5 um
    est = run_with_progress(iter_estimate(image, psf_radius=r))
    op, meta = est.operator, est.operator.metadata
    # measured: 103 beads used, I = 4, 2 saturated beads excluded
    assert meta["n_beads_used"] >= 60
    assert est.beads.counts()["saturated"] >= 1
    # lateral FWHM, measured 303-312 nm across the field: a 1.4 NA confocal imaging beads
    for y, x in [(200, 200), (512, 512), (800, 800)]:
        psf = op.psf_at(y, x)
        c = psf.shape[0] // 2
        fwhm_nm = 1000 * info.pixel_size * _fwhm(psf[c])
        assert 200 < fwhm_nm < 450, (y, x, fwhm_nm)
    h = meta["heldout"]
    # measured: held-out residual 0.141 against a noise floor of 0.032 -- a misfit the
    # residual analysis (issue 4) has to explain; here it must stay a sane model
    assert h["noise_floor_mean"] < h["residual_mean"] < 0.25


def test_sp8_diagnosis_traces_the_residual(sp8):
    """The loop on measured beads: the held-out residual is traced to companions merged
    with beads and to beads of different sizes (the brightest fifth are wider), and each
    lowers the held-out error (docs/measured/sp8_confocal_beads)."""
    from napari_psfspace.core.diagnose import diagnose

    z, image, info = sp8
    d = diagnose(image, psf_radius=0.5 / info.pixel_size)
    assert {"neighbours", "bead_size"} <= set(d.added)
    for name in ("neighbours", "bead_size"):
        step = next(s for s in d.steps if s.effect == name)
        # measured: 0.0413 -> 0.0333 (neighbours), 0.0333 -> 0.0280 (bead size)
        assert step.paired_after < 0.9 * step.paired_before
        assert step.p_no_drop <= 0.005
    assert d.error_after < 0.75 * d.error_before
    assert d.error_after > d.noise_floor  # and it says what is left: not at the floor
