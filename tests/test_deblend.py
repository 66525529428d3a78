"""The crowded field's deblending: each detection's light fitted with the model's PSF."""

import numpy as np

from napari_psfspace.core.model.deblend import ModelLight, deblend, fit_light

SIZE = 21


def _psf():
    g = np.arange(SIZE) - SIZE // 2
    psf = np.exp(-0.5 * (g[:, None] ** 2 / 2.0**2 + g[None, :] ** 2 / 4.0**2))
    return psf / psf.sum()


class Constant:  # a model whose PSF is the same everywhere
    psf_size = SIZE

    def psf_at(self, y, x):
        return _psf()


def _image(positions, flux, background=100.0, shape=(80, 100)):
    """Beads at whole pixels (the PSF's own samples, so the model is exact) on a flat
    background."""
    image = np.full(shape, background)
    h, c = _psf(), SIZE // 2
    for (y, x), f in zip(positions.astype(int), flux, strict=True):
        image[y - c:y + c + 1, x - c:x + c + 1] += f * h
    return image


def test_overlapping_beads_light_is_fitted_exactly():
    """Three beads whose PSFs overlap (6 px apart along the PSF's long axis), and one
    detection on bare background: started a factor of 10 off, the Gauss-Seidel sweeps
    converge to the light drawn (each sweep's error shrinks by a factor set by the
    neighbours' overlap, about 3 here; 50 sweeps leave it far under 1e-8), and the empty
    detection's light is 0, not negative."""
    pos = np.array([[40.0, 30.0], [40.0, 36.0], [40.0, 42.0], [40.0, 75.0]])
    flux = np.array([1e4, 3e3, 6e3, 0.0])
    light = ModelLight(Constant(), pos, np.full(4, 10.0))
    fit_light(light, _image(pos, flux), 8.0, passes=50)
    np.testing.assert_allclose(light.flux[:3], flux[:3], rtol=1e-8)
    assert 0.0 <= light.flux[3] < 1e-6 * flux.max()


def test_the_light_is_the_models_not_the_cores():
    """Started from no light at all, every sweep comes closer to the light drawn (the
    fits use the neighbours' latest light: Gauss-Seidel on overlapping PSFs does not
    overshoot, as holding them at the last sweep's does)."""
    pos = np.array([[40.0, 30.0], [40.0, 36.0], [40.0, 42.0]])
    flux = np.array([1e4, 3e3, 6e3])
    image = _image(pos, flux)
    errs = []
    for passes in (1, 2, 3, 6):
        light = ModelLight(Constant(), pos, np.zeros(3))
        fit_light(light, image, 8.0, passes=passes)
        errs.append(np.max(np.abs(light.flux / flux - 1)))
    assert all(b <= a for a, b in zip(errs, errs[1:], strict=False))
    assert errs[-1] < errs[0]


def test_deblend_cuts_once_per_pass_and_stops_when_nothing_is_left():
    class Beads:
        positions = np.array([[40.0, 30.0], [40.0, 36.0]])
        status = np.zeros(2, int)

    calls = []

    def cut(light, kept):
        calls.append(light)
        return np.array([0]), None

    out = deblend(None, np.array([0, 1]), np.zeros((80, 100)), Beads(), 8.0, cut, passes=0)
    assert out[0].tolist() == [0, 1] and out[1] is None and not calls


def test_deblend_stops_when_the_light_settles(monkeypatch):
    """A light that halves its distance to the truth each pass (as the fields measured
    do): from 8 % off, the relative changes between passes are 0.04 / 1.04, 0.02 / 1.02
    and 0.01 / 1.01, so the fourth pass's is the first under the 1 % tolerance; a light
    that never settles runs the most passes."""
    import napari_psfspace.core.model.deblend as dm

    class Beads:
        positions = np.zeros((3, 2))
        status = np.zeros(3, int)

    truth = np.array([1e3, 2e3, 4e3])

    def fake(errors):
        state = {"k": 0}

        def model_light(patches, image, beads, psf_radius, light=None):
            err = errors(state["k"])
            state["k"] += 1
            return ModelLight(Constant(), beads.positions, truth * (1 + err))

        return state, model_light

    cuts = []
    state, ml = fake(lambda k: 0.08 / 2**k)
    monkeypatch.setattr(dm, "model_light", ml)
    deblend("p", np.array([0]), None, Beads(), 8.0, lambda light, kept: cuts.append(1) or (0, "p"))
    assert state["k"] == 4 and len(cuts) == 4
    state, ml = fake(lambda k: 0.08 * (-1) ** k)
    monkeypatch.setattr(dm, "model_light", ml)
    deblend("p", np.array([0]), None, Beads(), 8.0, lambda light, kept: (0, "p"))
    assert state["k"] == dm.DEBLEND_PASSES



def test_each_cut_takes_the_last_cuts_beads(monkeypatch):
    """A bead one cut leaves out (faint: its status says so) is not cut again by the
    next pass: each cut is handed the beads the last one returned."""
    import napari_psfspace.core.model.deblend as dm

    class Beads:
        positions = np.zeros((4, 2))
        status = np.zeros(4, int)

    k = {"n": 0}

    def model_light(patches, image, beads, psf_radius, light=None):
        k["n"] += 1  # a light that never settles: every pass runs
        return ModelLight(Constant(), beads.positions, np.full(4, 100.0 * (-1) ** k["n"] + 200))

    monkeypatch.setattr(dm, "model_light", model_light)
    handed = []

    def cut(light, kept):
        handed.append(kept.tolist())
        return kept[1:], "p"  # each cut leaves one more bead out

    kept, _ = deblend("p", np.arange(4), None, Beads(), 8.0, cut, passes=3)
    assert handed == [[0, 1, 2, 3], [1, 2, 3], [2, 3]] and kept.tolist() == [3]
