"""The family is never worse than one image's own estimate (issue 24, point 2).

Each image with enough beads is judged on held-out beads of its own: it keeps the
family's operator only where that explains them at least as well as its own estimate
(core/family/choice.py). The metric is bench_accuracy's aligned PSF error on a 4 x 4
grid, against each image's truth.
"""

import json

import numpy as np
import pytest

from napari_psfspace.core.family import OperatorFamily, estimate_family
from napari_psfspace.core.family.estimate import family_cone
from napari_psfspace.core.model.cone import reduce_cone
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.stacks import random_conditions, simulate_stack

#: Conditions over about +-1 depth of field at NA 1.3, tilts, spherical drift
#: (bench_family_oracle.py's WIDE).
WIDE = {"focus": 0.2, "tilt": 0.06, "spherical": 0.03}


def _errors(ops, truths):
    return np.array([float(np.mean(grid_errors(op, t, n=4))) for op, t in zip(ops, truths,
                                                                               strict=True)])


@pytest.fixture(scope="module")
def wide():
    """6 images of 512 x 512, about 40 bright beads each, wide conditions."""
    conds = random_conditions(6, [3, 1], WIDE)
    images, truths, _ = simulate_stack(6, (512, 512), 40, seed=3, conditions=conds)
    r = int(np.median([t.psf_radius for t in truths]))
    alone = [estimate_operator(im, psf_radius=r) for im in images]
    return images, truths, r, alone


def test_an_image_the_family_explains_worse_keeps_its_own_estimate(wide, tmp_path):
    """A family forced to one PSF shape cannot hold a wide focus series: every image's
    held-out beads say so, and each keeps exactly what estimate_operator gives it."""
    images, truths, r, alone = wide
    sub = estimate_family(images, psf_radius=r, n_psf=1, n_space=1)
    choice = sub.metadata["operator_choice"]
    assert [c["model"] for c in choice] == ["own"] * len(images), choice
    assert all(c["heldout_own"] < c["heldout_family"] for c in choice)
    for k, op in enumerate(alone):
        np.testing.assert_allclose(sub.operator(k).psf_at(200.0, 300.0), op.psf_at(200.0, 300.0),
                                   atol=1e-12)
    # the reported held-out error is the kept operator's
    assert sub.metadata["heldout"][0]["residual_mean"] == pytest.approx(
        choice[0]["heldout_own"])
    # the file keeps them, without pickle
    path = tmp_path / "family.npz"
    sub.save(path)
    back = OperatorFamily.load(path)
    assert sorted(back.own) == list(range(len(images)))
    for k in (0, 5):
        np.testing.assert_array_equal(back.operator(k).psf_at(100.0, 50.0),
                                      sub.operator(k).psf_at(100.0, 50.0))
    np.testing.assert_array_equal(back.gammas, sub.gammas)


def test_a_version_1_file_reads_as_a_family_without_own_operators(wide, tmp_path):
    images, _, r, _ = wide
    sub = estimate_family(images[:3], psf_radius=r, holdout=None)
    assert sub.own == {} and sub.metadata["operator_choice"] is None
    path = tmp_path / "v2.npz"
    sub.save(path)
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files if not k.startswith("own_")}
    header = json.loads(arrays.pop("header").tobytes().decode("utf-8"))
    header["version"] = 1
    old = tmp_path / "v1.npz"
    np.savez(old, **arrays, header=np.frombuffer(json.dumps(header).encode(), np.uint8))
    back = OperatorFamily.load(old)
    assert back.own == {}
    np.testing.assert_array_equal(back.operator(1).psf_at(9.0, 9.0),
                                  sub.operator(1).psf_at(9.0, 9.0))


def test_a_damaged_version_2_file_names_what_is_wrong(wide, tmp_path):
    images, _, r, _ = wide
    sub = estimate_family(images[:3], psf_radius=r, n_psf=1, n_space=1)
    assert sub.own  # the family forced to one PSF: the images keep their own estimates
    path = tmp_path / "family.npz"
    sub.save(path)
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    k = int(arrays["own_images"][0])
    for name, bad, message in (
            ("family_weights", np.array([0.5, 2.0]), "family weights"),
            (f"own_{k}_basis", None, "missing entries"),
            (f"own_{k}_coefficients", np.zeros((2, 3, 3)), f"image {k}'s own operator")):
        damaged = dict(arrays)
        if bad is None:
            del damaged[name]
        else:
            damaged[name] = bad
        out = tmp_path / f"damaged_{name}.npz"
        np.savez(out, **damaged)
        with pytest.raises(ValueError, match=message):
            OperatorFamily.load(out)


def test_a_wide_focus_series_is_never_worse_in_the_family(wide):
    """Bright dense images over a wide focus range: the family with the paper's 20
    cone generators was 1.17-1.82x one image's error (bench_family_oracle.py). Now every
    image is within the own estimate's error (the family kept where its held-out beads
    say it is at least as good) and the mean is no worse."""
    images, truths, r, alone = wide
    sub = estimate_family(images, psf_radius=r)
    ratio = _errors([sub.operator(k) for k in range(len(images))], truths) \
        / _errors(alone, truths)
    # measured 1.00, 0.69, 0.95, 1.00, 0.56, 0.83 with issue 45's neighbour rule (mean
    # 0.84; before it 0.93, 0.73, 0.99, 1.00, 0.60, 0.87; the family alone: 0.94,
    # 0.74, 0.99, 1.41, 0.60, 0.87). A blend is kept only where 8 held-out beads show
    # it better beyond their scatter: it could still lose by what they cannot see, so
    # the bound is the issue's, not a guarantee (bench/RESULTS.md: 3 seeds, 2 sizes)
    assert ratio.max() <= 1.0 + 1e-6, ratio
    assert ratio.mean() <= 0.9, ratio
    # bright beads (noise floors far below the range where the prior leans to the
    # family): each image's prior weight is its share's, the even blend or near it
    priors = [c["prior_weight"] for c in sub.metadata["operator_choice"]
              if c.get("prior_weight") is not None]
    assert priors and max(priors) <= 0.55, priors


def test_the_family_cone_holds_every_image_own_cone():
    rng = np.random.default_rng(0)
    coef = np.concatenate([rng.normal(0, 1, (30, 4)) + [5 * k, 1, 0, 0] for k in range(3)])
    owner = np.repeat(np.arange(3), 30)
    cone = family_cone(coef, owner)
    for k in range(3):
        own = reduce_cone(coef[owner == k]).generators
        # every generator of an image's own cone is inside the family's cone
        np.testing.assert_allclose(cone.project(own), own, atol=1e-9)
    assert len(cone.generators) <= 20 * 3


@pytest.mark.parametrize("name,first,last,radius", [
    ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", 27, 39, 10.0),
    ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", 28, 34, None),
])
def test_measured_slices_are_never_worse_in_the_family(shared_data, name, first, last,
                                                       radius):
    """Issue 24: each slice's family operator explains its held-out beads at least as
    well as its own estimate on the same beads (by construction: its own estimate is
    the weight-0 candidate, and it stays unless a blend does better beyond the beads'
    scatter). The slice's own estimate inside the family is estimate_operator's:
    the same beads, split and model (measured: equal to 4 digits on every slice)."""
    from napari_psfspace.io import read_image

    path = shared_data / name
    slices = [read_image(path, index=z)[0] for z in range(first, last)]
    r = radius if radius is not None else 0.5 / read_image(path, index=first)[1].pixel_size
    sub = estimate_family(slices, psf_radius=r)
    choice = sub.metadata["operator_choice"]
    for k, z in enumerate(sub.metadata["images"]):
        alone = estimate_operator(slices[z], psf_radius=r).metadata["heldout"]
        own = choice[k]["heldout_by_weight"]["0"]
        # the family's own candidate is the slice's estimate, judged on its beads
        assert own == pytest.approx(alone["residual_mean"], rel=1e-9), (first + z, own,
                                                                          alone)
        kept = sub.metadata["heldout"][k]["residual_mean"]
        assert kept <= alone["residual_mean"] * (1 + 1e-12), (first + z, kept, alone)
    # not a tie everywhere: the family helps on some slices
    assert any(c["family_weight"] > 0 for c in choice)


def test_too_few_beads_left_for_the_held_out_family_keeps_the_family():
    """Faint stacks leave few usable beads: the family learnt without the held-out ones
    may have too few for its basis. Then no image is judged (each keeps the family, the
    paper's model) instead of the learning failing; with too few beads for any family,
    the error names the count per image."""
    images, truths, _ = simulate_stack(2, (384, 384), 6, seed=0)
    r = int(np.median([t.psf_radius for t in truths]))
    sub = estimate_family(images, psf_radius=r, n_psf=3, holdout=0.5)
    assert sum(sub.metadata["beads_per_image"]) >= 8  # enough for the family itself
    assert sub.n_psf == 3
    assert [c["model"] for c in sub.metadata["operator_choice"]] == ["family"] * 2
    assert sub.family_weights.tolist() == [1.0, 1.0]
    sparse, _, _ = simulate_stack(2, (256, 256), 2, seed=0)
    with pytest.raises(ValueError, match=r"at least 5 usable beads over all images, got \d"):
        estimate_family(sparse, psf_radius=r)
    with pytest.raises(ValueError, match=r"`n_psf` = 9 needs at least 20 usable beads"):
        estimate_family(images, psf_radius=r, n_psf=9)


def _curve(means, sd, n=20):
    """Per-bead residuals at each weight (deterministic): a common bead term (the beads
    differ far more from each other than the weights do, as held-out residuals do), the
    weight's mean, and a scatter of +-``sd`` whose sign alternates over the beads and
    flips from one weight to the next (paired differences of neighbouring weights
    scatter by 2 sd, of weights two apart not at all)."""
    from napari_psfspace.core.family.choice import WEIGHTS
    base = np.linspace(0.1, 0.3, n)
    signs = (-1.0) ** np.arange(n)
    return {w: base + m + sd * signs * (-1.0) ** round(4 * w)
            for w, m in zip(WEIGHTS, means, strict=True)}


def test_a_flat_held_out_curve_keeps_the_prior_weight():
    from napari_psfspace.core.family.choice import PRIOR_WEIGHT, pick_weight
    # minimum at 0.75 by less than the paired scatter: the prior (the even blend) is kept
    curve = _curve([0.010, 0.004, 0.0005, 0.0, 0.0008], sd=0.005)
    assert pick_weight(curve, prior=0.5) == (0.5, True)
    assert pick_weight(curve) == pick_weight(curve, prior=PRIOR_WEIGHT)  # the default
    # a prior on the family's side: 0.75
    w, beaten = pick_weight(_curve([0.010, 0.004, 0.0, 0.0005, 0.0008], sd=0.005),
                            prior=0.75)
    assert (w, beaten) == (0.75, True)


def test_the_prior_leans_to_the_family_as_the_image_s_share_of_its_field_falls():
    from napari_psfspace.core.family.choice import PRIOR_WEIGHT, prior_weight
    from napari_psfspace.core.family.shrink import Fields
    assert prior_weight(1.0) == PRIOR_WEIGHT and prior_weight(0.0) == 1.0
    assert prior_weight(0.5) == pytest.approx(1 - 0.5 * (1 - PRIOR_WEIGHT))  # linear
    assert prior_weight(float("nan")) == PRIOR_WEIGHT  # unknown: the even blend
    assert prior_weight(1.7) == PRIOR_WEIGHT and prior_weight(-1.0) == 1.0
    # the share: shrink factors weighted by the columns' spread; no spread: their mean
    f = Fields([], [], np.array([[1.0, 0.0], [0.5, 0.5]]), np.array([3.0, 1.0]))
    assert np.allclose(f.share(), [0.75, 0.5])
    f0 = Fields([], [], np.array([[0.0, 0.0], [0.0, 0.0]]), np.zeros(2))
    assert np.allclose(f0.share(), [0.0, 0.0])


def test_the_prior_leans_to_the_family_where_the_beads_are_mostly_noise():
    from napari_psfspace.core.family.choice import NOISE_FLOOR_RANGE, PRIOR_WEIGHT, prior_weight
    lo, hi = NOISE_FLOOR_RANGE
    # a bright image whose beads determine its departure: the even blend
    assert prior_weight(1.0, 0.0) == PRIOR_WEIGHT
    assert prior_weight(1.0, lo) == PRIOR_WEIGHT
    # faint beads: the family's operator, whatever the share
    assert prior_weight(1.0, hi) == 1.0 and prior_weight(1.0, 0.97) == 1.0
    assert prior_weight(1.0, (lo + hi) / 2) == pytest.approx((1 + PRIOR_WEIGHT) / 2)
    # the larger of the two leanings
    assert prior_weight(0.0, 0.0) == 1.0
    p = PRIOR_WEIGHT
    for share in (0.5, 0.2):  # the share's leaning against the floor's (a quarter up)
        assert prior_weight(share, lo + 0.25 * (hi - lo)) == pytest.approx(
            max(1 - (1 - p) * share, p + (1 - p) * 0.25))
    # an unknown floor: the share's alone
    assert prior_weight(0.5, float("nan")) == pytest.approx(1 - (1 - p) * 0.5)


def test_the_noise_floor_is_the_held_out_residuals_floor():
    from napari_psfspace.core.beads.patches import extract_patches
    from napari_psfspace.core.model.heldout import noise_floors, residuals_of
    from napari_psfspace.core.simulation import simulate_beads

    image, truth = simulate_beads((256, 256), 12, seed=4, amplitude=(1e3, 3e3))
    r = float(truth.psf_radius)
    patches = extract_patches(image, truth.positions, r)
    floors = noise_floors(patches)
    models = np.ones((len(patches), patches.size, patches.size))
    assert np.array_equal(floors, residuals_of(models, patches).noise_floor)
    assert floors.shape == (len(patches),) and np.all((floors > 0) & (floors < 1))


def test_faint_images_lean_to_the_family_where_their_held_out_beads_are_noise():
    """Bead photons 1,200-1,800 (issue 11's faint stacks, bench_family_oracle.py --photons
    0.06): a bead's windowed noise is 0.8-0.9 of its norm, the image's own estimate 1.3-2
    times the family's error. The empirical Bayes share of such an image's field stayed
    high on pyotf's stacks (departures consistent over its beads that bring its PSFs no
    closer to the truth), so the blend leant to the even one; the beads' noise now leans
    it to the family (bench/RESULTS.md)."""
    images, truths, _ = simulate_stack(6, (512, 512), 40, seed=1, amplitude=(1200.0, 1800.0))
    r = int(np.median([t.psf_radius for t in truths]))
    sub = estimate_family(images, psf_radius=r)
    choices = sub.metadata["operator_choice"]
    priors = [c["prior_weight"] for c in choices]
    # measured 0.94-1.00 (the share's alone: 0.61-0.86)
    assert min(priors) >= 0.9, priors
    alone = _errors([estimate_operator(im, psf_radius=r) for im in images], truths)
    ratio = _errors([sub.operator(k) for k in range(len(images))], truths) / alone
    # measured 0.57-0.81, mean 0.70 (the share's prior alone: 0.71)
    assert ratio.max() <= 1.0, ratio
    assert ratio.mean() <= 0.75, ratio


def test_beads_that_are_mostly_noise_turn_the_burden_of_proof():
    from napari_psfspace.core.family.choice import pick_weight
    # every blend ahead of the own estimate by less than the scatter, 0.5 ahead of the
    # other blends beyond theirs (none): the own estimate stays where the beads can
    # judge; where they are mostly noise, the best blend (the own is within its scatter)
    res = _curve([0.002, 0.001, 0.0, 0.001, 0.002], sd=0.0)
    for w in (0.25, 0.5, 0.75, 1.0):
        res[w] = res[w] + 0.01 * (-1.0) ** np.arange(20)
    assert pick_weight(res, prior=1.0)[0] == 0.0
    assert pick_weight(res, prior=1.0, faint=True) == (0.5, True)
    # a flat curve: the same
    flat = _curve([0.0, 0.0, 0.0, 0.0, 0.0], sd=0.005)
    assert pick_weight(flat, prior=1.0)[0] == 0.0
    assert pick_weight(flat, prior=1.0, faint=True) == (1.0, True)
    # the own estimate better than every other weight beyond the scatter: it stays
    clear = _curve([0.0, 0.01, 0.02, 0.03, 0.05], sd=0.002)
    assert pick_weight(clear, prior=1.0, faint=True)[0] == 0.0
    # the own estimate better than the family alone beyond the scatter but not than
    # 0.25 (paired scatter 2 sd / sqrt(20) = 0.0009 against 0.0005): 0.25
    near = _curve([0.0, 0.0005, 0.02, 0.03, 0.05], sd=0.002)
    assert pick_weight(near, prior=1.0, faint=True)[0] == 0.25


def test_a_clear_minimum_is_kept_and_a_weak_one_keeps_the_own_estimate():
    from napari_psfspace.core.family.choice import pick_weight
    # the family alone better beyond the scatter: the family
    w, beaten = pick_weight(_curve([0.05, 0.04, 0.03, 0.015, 0.0], sd=0.002))
    assert (w, beaten) == (1.0, True)
    # the own estimate clearly best: 0
    w, beaten = pick_weight(_curve([0.0, 0.01, 0.02, 0.03, 0.05], sd=0.002))
    assert w == 0.0
    # every blend ahead of the own estimate by less than the scatter of their paired
    # differences (the blends share a term the own estimate does not): 0 is kept
    res = _curve([0.002, 0.001, 0.0, 0.001, 0.002], sd=0.0)
    for w in (0.25, 0.5, 0.75, 1.0):
        res[w] = res[w] + 0.01 * (-1.0) ** np.arange(20)
    w, beaten = pick_weight(res)
    assert w == 0.0
    # one blend beats it beyond the scatter, the prior's does not: that blend
    res[0.25] = res[0.25] - 0.01 * (-1.0) ** np.arange(20)
    w, beaten = pick_weight(res)
    assert (w, beaten) == (0.25, True)


def test_an_own_estimate_asked_only_at_held_out_beads_is_the_full_one_there(wide):
    """The judgement's own estimate is assembled only around the held-out beads: its
    PSFs there are the full estimate's, to the last digit (each node is kept in the cone
    by itself, and the PSF at a bead is its four nodes'), and the field can differ
    elsewhere (nodes far from them are not projected)."""
    from napari_psfspace.core.family.choice import own_estimate
    from napari_psfspace.core.family.patches import image_patches
    from napari_psfspace.core.model.heldout import split_holdout

    images, _, r, _ = wide
    found = image_patches(images[0], float(r), index=0)
    mask = split_holdout(found.patches.centers, found.shape, 0.2)
    train, held = found.patches.subset(~mask), found.patches.subset(mask)
    full = own_estimate(train, found.shape)
    near = own_estimate(train, found.shape, at=held.centers)
    assert full is not None and near is not None and mask.sum() >= 5
    for y, x in held.centers:
        np.testing.assert_array_equal(near.psf_at(y, x), full.psf_at(y, x))
