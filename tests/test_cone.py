"""Tests of the conic-hull projection (core/cone.py, paper Appendix C)."""

from itertools import combinations

import numpy as np
import pytest
from scipy.optimize import nnls

from napari_psfspace.core.model.cone import Cone, project_onto_cone, reduce_cone


def _brute_projection(a, g):
    """Exact projection onto cone(g) by enumerating active sets (small k only)."""
    best, best_d = np.zeros_like(a), float(np.dot(a, a))
    for size in range(1, len(g) + 1):
        for idx in combinations(range(len(g)), size):
            sub = g[list(idx)]
            lam = np.linalg.lstsq(sub.T, a, rcond=None)[0]
            if np.all(lam >= -1e-12):
                p = lam @ sub
                d = float(np.sum((a - p) ** 2))
                if d < best_d:
                    best, best_d = p, d
    return best


def _generators(seed, k=4, dim=5):
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((k, dim)) + 2.0 * np.eye(k, dim)  # well conditioned, k <= I
    return g / np.linalg.norm(g, axis=1, keepdims=True), rng


def test_nnls_matches_brute_force():
    g, rng = _generators(0)
    a = rng.standard_normal((40, 5))
    proj = project_onto_cone(a, g)
    brute = np.array([_brute_projection(row, g) for row in a])
    direct = np.array([nnls(g.T, row)[0] @ g for row in a])
    # measured 3e-15 on seed 0 (all 40 points outside the cone)
    assert np.abs(proj - brute).max() < 1e-8
    assert np.abs(proj - direct).max() < 1e-8
    # optimality: the residual is orthogonal to the projection and points away
    # from every generator (KKT conditions of the projection onto a cone)
    resid = a - proj
    assert np.abs(np.einsum("ij,ij->i", resid, proj)).max() < 1e-10
    assert (resid @ g.T).max() < 1e-10


def test_points_inside_unchanged():
    g, rng = _generators(2)
    inside = rng.uniform(0.1, 2.0, (30, len(g))) @ g
    proj = project_onto_cone(inside, g)
    # measured 6e-16
    assert np.abs(proj - inside).max() < 1e-10 * np.abs(inside).max()


def test_idempotent():
    g, rng = _generators(3)
    a = rng.standard_normal((30, 5))
    once = project_onto_cone(a, g)
    twice = project_onto_cone(once, g)
    # measured 7e-16
    assert np.abs(twice - once).max() < 1e-8


def test_opposite_point_projects_to_origin():
    g, _ = _generators(4)
    a = -(np.ones(len(g)) @ g)[None, :]
    # -sum(g) makes a non-positive inner product with every generator here
    assert np.all(a @ g.T <= 0)
    assert np.abs(project_onto_cone(a, g)).max() < 1e-12


def test_invalid_arguments():
    g, _ = _generators(5)
    with pytest.raises(ValueError, match="`points`.*`generators`"):
        project_onto_cone(np.zeros((3, 4)), g)
    with pytest.raises(ValueError, match="`coefficients`"):
        reduce_cone(np.zeros((0, 3)))


def _data_vectors(seed, n=200, dim=4, n_rays=8):
    """Non-negative combinations of a few hidden extreme rays in the positive orthant."""
    rng = np.random.default_rng(seed)
    rays = np.abs(rng.standard_normal((n_rays, dim))) + 0.2
    w = rng.exponential(1.0, (n, n_rays)) * (rng.random((n, n_rays)) < 0.4)
    w[w.sum(axis=1) == 0, 0] = 1.0
    return w @ rays


def test_reduce_cone_covers_data():
    b = _data_vectors(0)
    tol = np.deg2rad(0.5)
    cone = reduce_cone(b, max_generators=60, angle_tol=tol)
    g = cone.generators
    assert len(g) <= 60
    assert np.abs(np.linalg.norm(g, axis=1) - 1).max() < 1e-12
    # angle of each data vector to the reduced cone, by an independent projection
    unit = b / np.linalg.norm(b, axis=1, keepdims=True)
    proj = np.array([nnls(g.T, u)[0] @ g for u in unit])
    ang = np.arccos(np.clip(np.linalg.norm(proj, axis=1), -1, 1))
    # measured max 0.487 deg with 11 generators on seed 0 (stops once <= 0.5 deg)
    assert ang.max() <= tol + 1e-9
    assert np.allclose(cone.angle(b), ang, atol=1e-6)
    # every generator after the first (the mean direction) is an observed direction
    d = np.abs(g[1:] @ unit.T - 1).min(axis=1)
    assert d.max() < 1e-12


def test_reduce_cone_respects_max_generators():
    b = _data_vectors(1)
    for cap in (1, 3, 5):
        cone = reduce_cone(b, max_generators=cap, angle_tol=np.deg2rad(1e-3))
        assert len(cone.generators) == cap
    # the first generator is the normalised mean direction
    unit = b / np.linalg.norm(b, axis=1, keepdims=True)
    mean = unit.mean(axis=0)
    assert np.abs(reduce_cone(b, max_generators=1).generators[0]
                  - mean / np.linalg.norm(mean)).max() < 1e-12


def _greedy_every_angle(b, max_generators, angle_tol):
    """The greedy reduced hull recomputing every vector's angle at each step (the
    paper's rule as written): the reference of the lazy one."""
    unit = b / np.linalg.norm(b, axis=1, keepdims=True)
    mean = unit.mean(axis=0)
    gens = [mean / np.linalg.norm(mean)]
    while len(gens) < max_generators:
        g = np.array(gens)
        proj = np.array([nnls(g.T, u)[0] @ g for u in unit])
        ang = np.arccos(np.clip(np.linalg.norm(proj, axis=1), -1, 1))
        if ang.max() <= angle_tol:
            break
        gens.append(unit[int(np.argmax(ang))])
    return np.array(gens)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reduce_cone_picks_the_generators_of_recomputing_every_angle(seed):
    # the lazy greedy skips vectors whose last angle is below the largest found: it must
    # pick the same generators, in the same order, as recomputing every angle
    rng = np.random.default_rng(seed)
    n_i = 4 + 3 * seed
    b = np.abs(rng.normal(size=(120, n_i))) + rng.normal(scale=0.3, size=(120, n_i))
    for cap, tol in ((20, np.deg2rad(0.5)), (60, np.deg2rad(5.0))):
        lazy = reduce_cone(b, max_generators=cap, angle_tol=tol).generators
        every = _greedy_every_angle(b, cap, tol)
        assert lazy.shape == every.shape
        assert np.abs(lazy - every).max() < 1e-12


def test_cone_project_and_angle():
    g, rng = _generators(6)
    cone = Cone(g)
    inside = rng.uniform(0.1, 1.0, (5, len(g))) @ g
    assert np.abs(cone.angle(inside)).max() < 1e-6  # measured 0 (arccos(1))
    assert np.abs(cone.project(inside) - inside).max() < 1e-12


# --- where the field needs the cone (issue 45) ---------------------------------------

def _gaussian_basis(p=21):
    """Two basis images: a Gaussian and a wider one minus it (a zero-sum ring)."""
    yy, xx = np.mgrid[:p, :p] - p // 2
    g1 = np.exp(-(yy ** 2 + xx ** 2) / (2 * 1.5 ** 2))
    g2 = np.exp(-(yy ** 2 + xx ** 2) / (2 * 3.0 ** 2))
    g1, g2 = g1 / g1.sum(), g2 / g2.sum()
    return np.stack([g1, g2 - g1])


def test_negative_share_is_the_negative_mass_over_the_positive():
    from napari_psfspace.core.model.cone import negative_share

    h = _gaussian_basis()
    # 1 * g1 + 0.5 (g2 - g1) = 0.5 g1 + 0.5 g2 >= 0; 1 * g1 - 1 * (g2 - g1) = 2 g1 - g2
    share = negative_share(np.array([[1.0, 0.5], [1.0, -1.0]]), h)
    v = 2 * h[0] - (h[0] + h[1])
    assert share[0] == 0.0
    assert share[1] == pytest.approx(-v[v < 0].sum() / v[v > 0].sum(), rel=1e-12)


def test_only_implausible_nodes_are_projected():
    """A field of coefficients that leaves the beads' range at some nodes: "where-needed"
    projects exactly the nodes whose PSF has a negative lobe beyond the beads' own and
    leaves every other node as "none" has it; "cone" moves the others too."""
    from napari_psfspace.core.model.cone import implausible, negative_share
    from napari_psfspace.core.model.field import assemble_operator

    h = _gaussian_basis()
    beta = np.column_stack([np.ones(5), np.linspace(0.0, 0.8, 5)])  # plausible beads
    shape = (128, 128)

    def field(nodes):  # the second coefficient runs from -1.5 to 1.5 across the columns
        return np.column_stack([np.ones(len(nodes)), 3 * nodes[:, 1] / shape[1] - 1.5])

    ops = {c: assemble_operator(h, beta, field, shape, grid_step=32, constraint=c)[0]
           for c in ("none", "where-needed", "cone")}
    maps = {c: op.coefficients.reshape(2, -1).T for c, op in ops.items()}
    bad = implausible(maps["none"], h, beta)
    assert 0 < bad.sum() < len(bad)
    np.testing.assert_allclose(maps["where-needed"][~bad], maps["none"][~bad], atol=1e-12)
    assert not np.allclose(maps["where-needed"][bad], maps["none"][bad])
    assert negative_share(maps["where-needed"], h).max() <= (
        1.5 * negative_share(beta, h).max() + 0.02 + 1e-9)
    assert not np.allclose(maps["cone"][~bad], maps["none"][~bad])


def test_the_held_out_beads_choose_the_cone_only_where_it_helps():
    from napari_psfspace.core.model.field import choose_constraint

    h = _gaussian_basis()
    rng = np.random.default_rng(0)
    beta = np.column_stack([np.ones(30), rng.uniform(0.0, 0.8, 30)])
    # predictions off the beads' own but inside their hull (shrunk to its middle): the
    # cone moves nothing, a tie, and the lighter rule is kept
    inside = beta.copy()
    inside[:, 1] = 0.4 + 0.9 * (beta[:, 1] - 0.4)
    chosen, scores = choose_constraint(beta, inside, h)
    assert scores["where-needed"] > 0
    assert chosen == "where-needed" and scores["where-needed"] == pytest.approx(scores["cone"])
    # a wild extrapolation (a deep negative lobe) is projected by either rule alike
    wild = beta.copy()
    wild[:, 1] = -3.0
    chosen, scores = choose_constraint(beta, wild, h)
    assert chosen == "where-needed" and scores["where-needed"] == pytest.approx(scores["cone"])
    # beads from 0.2 to 0.8 predicted 0.3 low: below 0.2 the predictions leave the
    # beads' hull while their PSFs stay plausible; the cone takes them back toward the
    # beads, and the held-out beads choose it
    beta[:, 1] = rng.uniform(0.2, 0.8, 30)
    low = beta - np.array([0.0, 0.3])
    chosen, scores = choose_constraint(beta, low, h)
    assert chosen == "cone" and scores["cone"] < 0.9 * scores["where-needed"]


def test_keep_in_cone_projects_what_each_rule_says():
    """The rule the 3D field uses (issue 45): "where-needed" moves only the implausible
    coefficients, onto the hull of every bead; "cone" all, onto the reduced cone;
    "none" nothing."""
    from napari_psfspace.core.model.cone import implausible
    from napari_psfspace.core.model.field import keep_in_cone

    h = _gaussian_basis()
    rng = np.random.default_rng(1)
    beta = np.column_stack([np.ones(30), rng.uniform(0.0, 0.8, 30)])
    coarse = np.column_stack([np.ones(40), np.linspace(-3.0, 1.5, 40)])
    bad = implausible(coarse, h, beta)
    assert 0 < bad.sum() < len(bad)
    none, _ = keep_in_cone(coarse, beta, h, "none")
    np.testing.assert_array_equal(none, coarse)
    where, cone = keep_in_cone(coarse, beta, h, "where-needed")
    np.testing.assert_array_equal(where[~bad], coarse[~bad])
    np.testing.assert_allclose(where[bad], cone.project(coarse[bad]))
    assert len(cone.generators) == len(beta)  # every bead's
    every, reduced = keep_in_cone(coarse, beta, h, "cone")
    np.testing.assert_allclose(every, reduced.project(coarse))
    assert not np.allclose(every[~bad], coarse[~bad])
