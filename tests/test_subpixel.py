"""Sub-pixel re-sampling by a Fourier phase ramp (``core/beads/subpixel``) and by the
patches' spline, against analytic Gaussian PSFs: band-limited interpolation is exact but
for the Gaussian's spectrum beyond Nyquist (aliasing) and for its tail where the taper
begins; a spline errs by a power of the frequency.
"""

import numpy as np
import pytest
from scipy import ndimage as ndi

from napari_psfspace.core.beads.centering import gather_windows
from napari_psfspace.core.beads.patches import resample_patches
from napari_psfspace.core.beads.subpixel import fourier_resample_patches

SIZE = 21  # the patch; the taper begins 10 pixels from the centre


def _scene(sd, centre, background=10.0):
    yy, xx = np.mgrid[0:96, 0:96]
    return background + np.exp(-((yy - centre[0]) ** 2 + (xx - centre[1]) ** 2)
                               / (2 * sd ** 2))


def _cubic(img, centre):
    """The patch re-sampled by a cubic spline, cut as the patches' spline cuts it."""
    win = gather_windows(img, centre[None], SIZE // 2 + 3)[0]
    g = np.arange(SIZE) + 3 + (centre - np.round(centre))[:, None]
    return ndi.map_coordinates(win, np.meshgrid(g[0], g[1], indexing="ij"), order=3,
                               mode="nearest")


def _truth(sd, background=10.0):
    g = np.arange(SIZE) - SIZE // 2
    return background + np.exp(-(g[:, None] ** 2 + g[None, :] ** 2) / (2 * sd ** 2))


@pytest.mark.parametrize("sd", [1.5, 2.5])
def test_a_gaussian_moved_by_a_fraction_of_a_pixel_is_sampled_on_its_centre(sd):
    """The error bound: the spectrum beyond Nyquist, ``2 exp(-pi^2 sd^2 / 2)`` of the
    peak, and the tail where the taper begins, ``exp(-10^2 / (2 sd^2))``."""
    rng = np.random.default_rng(int(sd * 10))
    bound = 2 * np.exp(-np.pi ** 2 * sd ** 2 / 2) + np.exp(-100 / (2 * sd ** 2))
    for centre in rng.uniform(38, 58, (6, 2)):
        img = _scene(sd, centre)
        got = fourier_resample_patches(img, centre[None], SIZE)[0]
        assert np.abs(got - _truth(sd)).max() <= bound
        # a cubic spline smooths beyond that bound where the move is large (the check
        # can fail): at sd 1.5 its error reaches 1e-3 of the peak
        if sd == 1.5 and np.abs(centre - np.round(centre)).max() > 0.3:
            assert np.abs(_cubic(img, centre) - _truth(sd)).max() > 10 * bound


def test_a_whole_pixel_centre_is_the_pixels_themselves():
    img = _scene(1.5, (48.0, 50.0)) + np.random.default_rng(1).normal(0, 0.1, (96, 96))
    got = fourier_resample_patches(img, np.array([[48.0, 50.0]]), SIZE)[0]
    assert np.allclose(got, img[38:59, 40:61], atol=1e-9)


def test_the_patches_spline_is_near_exact_on_a_smooth_psf():
    """The patches' spline (order 5) against the cubic on a Gaussian of sd 2.5 px: a
    spline of order ``n`` errs by about ``(w / pi) ** (n + 1)`` at frequency ``w``. The
    errors come from where the spectrum ``exp(-(w sd)**2 / 2)`` times that power peaks,
    ``w = sqrt(n + 1) / sd``: ``w / pi`` about 0.25 to 0.3, so the quintic's two more
    powers make its error about ten times smaller than the cubic's at least, and under
    3e-5 of the peak."""
    sd = 2.5
    rng = np.random.default_rng(25)
    for centre in rng.uniform(38, 58, (4, 2)):
        if np.abs(centre - np.round(centre)).max() < 0.1:
            continue
        img = _scene(sd, centre)
        got = resample_patches(img, centre[None], SIZE)[0]
        err, err3 = (np.abs(a - _truth(sd)).max() for a in (got, _cubic(img, centre)))
        assert err < 3e-5
        assert err3 > 10 * err
