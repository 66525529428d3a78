"""The family as a Gaussian prior over an image's field (core/restore/posterior.py, issue 45).

Known truths only: fields drawn from the prior itself, so that what the posterior should
give is known exactly (its mean recovers a field in the prior's span; its spread is the
error it makes on average).
"""

import numpy as np

from napari_psfspace.core.restore.posterior import (
    FieldPrior,
    bilinear,
    posterior_field,
    spatial_kernels,
)

SHAPE = (256, 256)


def _prior(rng, n_k=5, n_i=3, n=9):
    """A prior on a 9 x 9 grid: smooth random fields of ``n_i`` coefficients."""
    g = np.linspace(0, SHAPE[0] - 1, n)
    grid = (g, g)
    nodes = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    u = nodes / np.array(SHAPE) - 0.5
    poly = np.column_stack([np.ones(len(u)), u, u ** 2, u[:, :1] * u[:, 1:]])  # (G, 6)
    fields = np.einsum("gm,kmi->kgi", poly, rng.normal(size=(n_k, poly.shape[1], n_i)))
    fields[:, :, 0] += 4.0  # a dominant first coefficient, as a PSF's mean has
    mean = fields.mean(axis=0)
    span = (fields - mean) / np.sqrt(n_k - 1)
    flat = (fields - mean).reshape(-1, n_i)
    cov = flat.T @ flat / len(flat)
    cov += 0.05 * np.trace(cov) / n_i * np.eye(n_i)
    return FieldPrior(grid, SHAPE, mean, span, cov), nodes


def test_bilinear_weights_interpolate_exactly_at_and_between_nodes():
    rng = np.random.default_rng(0)
    prior, nodes = _prior(rng)
    w = bilinear(prior.grid, nodes)
    assert np.allclose(w, np.eye(len(nodes)))
    mid = (nodes[0] + nodes[10]) / 2  # the centre of the first cell
    assert np.allclose(bilinear(prior.grid, mid[None]) @ prior.mean,
                       prior.mean[[0, 1, 9, 10]].mean(axis=0))


def test_a_field_on_the_span_is_recovered_from_a_few_noise_free_beads():
    """A new condition that is a mix of the learnt ones, beyond their range (weights up
    to 2 sd): 6 noise-free beads give its field at every node."""
    rng = np.random.default_rng(1)
    prior, nodes = _prior(rng)
    w = rng.normal(0, 2.0, size=len(prior.span))
    truth = prior.mean + np.tensordot(w, prior.span, axes=1)  # (G, I)
    beads = nodes[rng.choice(len(nodes), 6, replace=False)]
    c = bilinear(prior.grid, beads) @ truth
    post = posterior_field(prior, c, beads, np.full(6, 1e-6), amplitude_range=(1.0, 1.0))
    err = np.linalg.norm(post.mean - truth) / np.linalg.norm(truth - prior.mean)
    # 18 equations, 5 weights: the span is determined and the evidence finds it (the
    # other parts' scales fall to their floor; measured error 2e-9). With the scales a
    # half of the truth's, the spread test below reads 2.7: both can fail
    assert err < 0.1
    assert post.scales["span"] > 10 * max(post.scales["affine"], post.scales["smooth"])


def _draw(prior, nodes, beads_idx, scales, rng):
    """A field drawn from the prior with the given scales, at the nodes (G, I)."""
    n_g, n_i = prior.mean.shape
    u = prior.scaled(nodes)
    w = rng.normal(size=len(prior.span))
    tilt = rng.normal(size=(2, len(prior.span)))
    field = prior.mean + scales[0] * np.tensordot(w, prior.span, axes=1)
    field += scales[1] * np.sqrt(12) * np.einsum(
        "gd,dk,kgi->gi", u, tilt, prior.span)
    ka, ks = spatial_kernels(u, u)
    lc = np.linalg.cholesky(prior.coef_cov)
    for s, k in zip(scales[2:], (ka, ks), strict=True):
        lk = np.linalg.cholesky(k + 1e-9 * np.eye(n_g))
        field += s * lk @ rng.normal(size=(n_g, n_i)) @ lc.T
    return field


def test_the_spread_is_the_error_the_posterior_makes_on_average():
    """Fields drawn from the prior (scales known), 5 noisy beads each: the squared error
    of the posterior mean at each node, over the spread's prediction of it, averages 1.

    The spread is ``sqrt(trace of the posterior covariance)`` over the mean's norm, so
    ``error^2 / (spread * norm)^2`` has mean 1 at every node; over 150 draws and the 81
    nodes (correlated: about 5 independent values per draw) its mean lies within 0.15
    of 1 (about 5 standard errors of ``sqrt(2 / (150 * 5))``)."""
    rng = np.random.default_rng(2)
    prior, nodes = _prior(rng)
    scales = np.array([1.0, 0.3, 0.2, 0.3])
    sd = 0.05
    ratios = []
    for _ in range(150):
        idx = rng.choice(len(nodes), 5, replace=False)
        truth = _draw(prior, nodes, idx, scales, rng)
        c = truth[idx] + rng.normal(0, sd, size=truth[idx].shape)
        post = posterior_field(prior, c, nodes[idx], np.full(5, sd),
                               amplitude_range=(1.0, 1.0), log_scales=np.log10(scales),
                               n_iter=1)
        err2 = ((post.mean - truth) ** 2).sum(axis=1)
        var = (post.spread * np.linalg.norm(post.mean, axis=1)) ** 2
        ratios.append(np.mean(err2 / var))
    assert abs(np.mean(ratios) - 1.0) < 0.15, np.mean(ratios)
    # and the spread is smallest where the beads are: at a bead, its noise; far, the prior
    far = np.argmax(np.min(np.hypot(*(nodes[:, None] - nodes[idx][None]).transpose(2, 0, 1)),
                           axis=1))
    assert post.spread[idx].max() < post.spread[far]
