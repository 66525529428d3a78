"""Learn a family of operators from many bead images (paper, sections 2.4 and 2.5).

Steps, on top of the single-image pipeline:

1. every image's bead patches (:func:`~.patches.image_patches`), one dask task per
   image, read one at a time;
2-4. one PCA of the patches of all images with outlier rejection (each bead against its
   own image's neighbours: the thin-plate fit of that image's beads, a gate for gross
   misfits on a robust scale) and a
   second PCA (:func:`~napari_psfspace.core.model.pca.learn_basis`); with ``denoise`` (the
   default) the PSF basis ``h_i`` is then learnt from each bead's value of its image's
   field of the first :data:`FIELD_COMPONENTS` ``x I`` components, with the family as the
   fields' prior (:mod:`.shrink`): faint beads' noise no longer picks the later
   components;
5. each image's coefficient maps on the coarse grid the single operator uses: its
   field with the family as prior (its own thin-plate field where its beads determine
   it, the family's mean field where they do not; ``denoise=False``: its own
   weighted thin-plate spline, the paper's step);
6-7. an SVD of all the maps of all images: the spatial basis ``a_j``;
8. ``Gamma_k[i, j] = <alpha_ik, a_j>`` (``refine=True`` refits each ``Gamma_k`` to its own
   beads' coefficients through the ``a_j`` instead: no better on dense stacks,
   ``bench/bench_subspace.py``, so off by default);
and the cone of the observed PSFs that every operator's PSFs are kept in (2.5): the union
of every image's own reduced cone (:func:`family_cone`);
9. (with a held-out split, the default) the family as a prior rather than a hard
constraint: each image with enough beads gets the blend of the family's operator and its
own single-image estimate that best explains beads of its own neither saw
(:mod:`.choice`), so that no image's operator is worse on them than its own estimate.

``I`` defaults to the Gavish-Donoho rule (``2.858 sigma_med`` for a square matrix,
:func:`~napari_psfspace.core.model.pca.rank_by_threshold`) on the raw patches whitened by
each bead's noise (:func:`~.sizes.white_rank`), ``J`` to the rule on the stacked maps;
both capped.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from ..beads.patches import R_EXT_FACTOR, patch_size
from ..beads.window import bump_window, radial_distance
from ..common.progress import Progress, wait_with_progress
from ..common.threads import blas_threads, compute_first, compute_tasks
from ..common.twins import drained
from ..common.validate import check_positive
from ..model.cone import Cone, reduce_cone
from ..model.denoise import band_limit, refit_basis
from ..model.field import coarse_grid
from ..model.pca import learn_basis, min_beads_for, orient, rank_by_threshold
from ..model.tps import ThinPlateSpline
from ..model.voronoi import voronoi_areas
from .choice import Choice, choose, own_estimate
from .dimensions import Beads, choose_dimensions, family_fields, noise_factor
from .patches import ImagePatches, extract_patches, hold_out, usable_images
from .result import OperatorFamily, space_at
from .shrink import Fields, shrunk_fields
from .sizes import family_sizes

#: Largest ``J`` the rule may choose.
MAX_SPACE = 16
#: ``I`` the field basis's principal components are counted for when ``I`` is not
#: given (:func:`pool`; the basis itself is bounded only by the beads).
FIELD_PSF = 12
#: Fewest beads for an image's own thin-plate map; below, its map is constant.
MIN_BEADS_TPS = 4
#: Principal components of the pooled patches whose fields (:mod:`.shrink`) the PSF
#: basis is learnt from, per component of the basis: the basis is chosen in their span.
FIELD_COMPONENTS = 2
#: Ridge of the refit of ``Gamma_k`` towards its projection, relative to the mean
#: diagonal of the beads' normal matrix.
REFIT_RIDGE = 1e-2


def _items(images) -> list:
    """The images as a list of arrays or zero-argument loaders (a 3-D array: its
    slices)."""
    if isinstance(images, np.ndarray):
        if images.ndim == 2:
            raise ValueError("`images` must hold several images (a list, or a 3-D stack "
                             "(K, H, W)); got one 2-D image: learn one operator with "
                             "estimate_operator instead")
        if images.ndim != 3:
            raise ValueError(f"`images` as an array must have shape (K, H, W), got "
                             f"{images.shape}")
        return [images[k] for k in range(images.shape[0])]
    if isinstance(images, (str, bytes)) or not isinstance(images, Sequence):
        raise ValueError("`images` must be a list of 2-D arrays or loaders, or a (K, H, W) "
                         f"stack; got {type(images).__name__}")
    return list(images)


def _image_map(centers: np.ndarray, coef: np.ndarray, nodes: np.ndarray,
               shape: tuple[int, int]) -> np.ndarray:
    """One image's coefficient maps at the grid's nodes from its beads (n, 2), (n, I);
    shape (G, I)."""
    if len(centers) < MIN_BEADS_TPS:
        return np.tile(coef.mean(axis=0), (len(nodes), 1))
    spline = ThinPlateSpline(centers, coef, weights=voronoi_areas(centers, shape),
                             scale=0.5 * float(np.hypot(*shape)))
    return np.asarray(spline(nodes), dtype=np.float64).reshape(len(nodes), -1)


def family_cone(coefficients: np.ndarray, owner: np.ndarray) -> Cone:
    """The union of each image's reduced cone of its beads' coefficients.

    One image's PSFs take about 20 generators (the paper's reduced cone); the family
    holds the PSFs of every condition. Reduced to 20 for all images together, the cone
    of a wide focus series leaves out much of each image's PSFs
    (``bench/bench_family_oracle.py``); the union keeps every image's own cone, so that no
    image's operator is held tighter than its own estimate would be.

    Parameters
    ----------
    coefficients : ndarray of shape (M, I)
        The beads' coefficients, all images.
    owner : ndarray of shape (M,)
        The image of each bead.

    Returns
    -------
    Cone
        At most ``20 K`` generators.
    """
    gens = [reduce_cone(coefficients[owner == k]).generators for k in np.unique(owner)]
    return Cone(np.concatenate(gens))


def _refit_gamma(gamma: np.ndarray, coef: np.ndarray, at: np.ndarray) -> np.ndarray:
    """``argmin ||coef - at Gamma^T||^2 + ridge ||Gamma - gamma||^2`` (I, J)."""
    n = at.T @ at  # (J, J)
    ridge = REFIT_RIDGE * max(float(np.trace(n)) / len(n), 1e-12)
    lhs = n + ridge * np.eye(len(n))
    rhs = at.T @ coef + ridge * gamma.T  # (J, I)
    return np.linalg.solve(lhs, rhs).T


@dataclass
class _Pooled:
    """The pooled patches of the images ``used`` and their PSF basis (steps 2-4)."""

    psf: np.ndarray  # (N, P, P) raw sum-1 patches of all images
    owner: np.ndarray  # (N,) position of each bead's image in ``used``
    sd: np.ndarray  # (N,) per-pixel noise / flux
    weights: np.ndarray | None
    window: np.ndarray
    support: np.ndarray
    basis: object  # PsfBasis
    fields: Fields | None = None  # each image's shrunk fields of the first components
    to_basis: np.ndarray | None = None  # (M, I): those components' coordinates -> h_i's


def _inlier_beads(used: list[ImagePatches], owner: np.ndarray, inliers: np.ndarray,
                  values: np.ndarray) -> tuple[list, list]:
    """Each image's inlier bead positions and their rows of ``values`` (inliers only, in
    image order)."""
    own_in = owner[inliers]
    centers = [f.patches.centers[inliers[owner == i]] for i, f in enumerate(used)]
    return centers, [values[own_in == i] for i in range(len(used))]


def _field_basis(used, learn, owner, weights, support, basis, grid, shape):
    """The PSF basis learnt from every inlier patch replaced by its image's shrunk field
    of the first :data:`FIELD_COMPONENTS` principal components (:mod:`.shrink`).

    Faint patches' noise swamps the PSFs' smaller variations, so the plain PCA's later
    components follow the noise; the fields average each bead with its neighbours and
    with the family, so the PCA sees the PSFs' variation over the field and over the
    conditions. The basis's coefficients stay those of the (band-limited) patches.
    """
    inl = basis.inliers
    comps = basis.components  # (M, S)
    x = learn[inl][:, support]
    coords = x @ comps.T  # (n_in, M)
    centers, values = _inlier_beads(used, owner, inl, coords)
    fields = shrunk_fields(centers, values, grid, shape)
    smooth = np.concatenate(fields.beads)  # (n_in, M), image order as ``coords``
    w = np.sqrt(weights[inl]) if weights is not None else np.ones(len(smooth))
    _, _, ut = np.linalg.svd(smooth * w[:, None], full_matrices=False)
    n_i = basis.basis.shape[0]
    flat = orient(ut[:n_i] @ comps)  # (I, S), orthonormal rows
    images = np.zeros_like(basis.basis)
    images[:, support] = flat
    new = replace(basis, basis=images, coefficients=x @ flat.T)
    return new, fields, comps @ flat.T


def pool(used: list[ImagePatches], n_psf, denoise: bool,
         grid: tuple[np.ndarray, np.ndarray] | None = None) -> _Pooled:
    """Steps 2-4: one (noise-aware) PCA of the patches of all images.

    With ``denoise``, the basis is learnt from each image's fields of its beads with the
    family as their prior (:func:`_field_basis`, on the coarse ``grid``, default that of
    a 32 px step), and so are the coefficient maps (:func:`coefficient_maps`).
    """
    psf = np.concatenate([f.patches.psf for f in used])
    owner = np.concatenate([np.full(f.n_beads, i) for i, f in enumerate(used)])
    first = used[0].patches
    window = bump_window(first.size, first.r, first.r_ext)
    support = radial_distance(first.size) < first.r_ext
    sd = np.concatenate([f.patches.noise / f.patches.flux for f in used])
    learn, weights = psf, None
    if denoise:  # as for one image: one Wiener filter, beads weighted by their noise
        weights = 1.0 / (psf[:, support] ** 2).sum(axis=1)
        learn, _ = band_limit(psf, sd, window)
    centers = np.concatenate([f.patches.centers for f in used])
    basis = learn_basis(learn, int(n_psf) if n_psf is not None else "rule", support=support,
                        weights=weights, svd="gram", positions=centers, groups=owner,
                        components=FIELD_COMPONENTS * (int(n_psf) if n_psf is not None
                                                       else FIELD_PSF) if denoise else 0)
    out = _Pooled(psf, owner, sd, weights, window, support, basis)
    if denoise and basis.components is not None and len(basis.components) >= basis.n_psf:
        shape = used[0].shape
        grid = grid if grid is not None else grid_nodes(shape, 32.0)[0]
        out.basis, out.fields, out.to_basis = _field_basis(
            used, learn, owner, weights, support, basis, grid, shape)
    return out


def coefficient_maps(used: list[ImagePatches], pooled: _Pooled, nodes: np.ndarray,
          shape: tuple[int, int]) -> tuple[list[np.ndarray], list[tuple]]:
    """Step 5: each image's coefficient maps at the nodes (G, I), and its inlier beads'
    (centers, coefficients).

    With the pooled fields (``denoise``), the maps are those fields on the basis: each
    image's own field where its beads determine it, the family's mean where they do not
    (:mod:`.shrink`); otherwise each image's own thin-plate field (the paper's step 5).
    """
    basis, owner = pooled.basis, pooled.owner
    centers, coefs = _inlier_beads(used, owner, basis.inliers, basis.coefficients)
    bead_coef = list(zip(centers, coefs, strict=True))
    if pooled.fields is not None:
        return [f @ pooled.to_basis for f in pooled.fields.nodes], bead_coef
    maps = []
    for c, a in bead_coef:
        if len(c):
            maps.append(_image_map(c, a, nodes, shape))  # (G, I)
        else:  # every bead of this image an outlier: the mean PSF of all
            maps.append(np.tile(basis.coefficients.mean(axis=0), (len(nodes), 1)))
    return maps, bead_coef


def grid_nodes(shape, grid_step):
    gy, gx = coarse_grid(shape, grid_step)
    return (gy, gx), np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)


def _learn(used: list[ImagePatches], shape: tuple[int, int], *, n_psf, n_space,
           grid_step: float, refine: bool, denoise: bool,
           dimensions: bool = False) -> OperatorFamily:
    """Steps 2-8 on the patches of the images ``used`` (each with beads); with
    ``dimensions``, the family's few dimensions too (:mod:`.dimensions`)."""
    (gy, gx), nodes = grid_nodes(shape, grid_step)
    pooled = pool(used, n_psf, denoise, grid=(gy, gx))
    basis, psf, sd, weights, window = (pooled.basis, pooled.psf, pooled.sd, pooled.weights,
                                       pooled.window)
    n_i = basis.basis.shape[0]
    maps, bead_coef = coefficient_maps(used, pooled, nodes, shape)
    stacked = np.concatenate([m.T for m in maps])  # (K I, G): one row per map alpha_ik
    _, s, vt = np.linalg.svd(stacked, full_matrices=False)
    if n_space is None:
        n_j = min(rank_by_threshold(s, stacked.shape)[0], MAX_SPACE, len(s))
    elif int(n_space) > len(s):
        raise ValueError(f"`n_space` = {n_space} is more spatial maps than the images give: "
                         f"at most {len(s)} ({len(maps)} images x {n_i} PSFs, "
                         f"{stacked.shape[1]} grid nodes)")
    else:
        n_j = int(n_space)
    space = vt[:n_j]  # (J, G), orthonormal rows
    gammas = np.stack([m.T @ space.T for m in maps])  # (K, I, J)
    space_grid = space.reshape(n_j, len(gy), len(gx))
    if refine:
        for k, (centers, coef) in enumerate(bead_coef):
            if len(centers) == 0:
                continue
            gammas[k] = _refit_gamma(gammas[k], coef, space_at(space_grid, (gy, gx), centers))
    images = basis.basis
    if denoise:
        # basis images refitted to the raw patches of all beads given each bead's own
        # coefficients. Given the family's coefficients at the beads instead (as one
        # image's operator does with its maps), the refit takes in the maps' errors and
        # loses to one image's own estimate on faint stacks (bench_subspace --noise)
        inl = basis.inliers
        at = np.concatenate([c for _, c in bead_coef])  # (n_inliers, I), image order
        images, _ = refit_basis(psf[inl], at, sd[inl], window, weights=weights[inl],
                                prior=basis.basis)
    cone = family_cone(basis.coefficients, pooled.owner[basis.inliers])
    meta = {
        "n_psf": int(n_i), "n_psf_rule": int(basis.n_psf_rule),
        "n_space": int(n_j), "n_space_rule": int(rank_by_threshold(s, stacked.shape)[0]),
        "refine": bool(refine), "denoise": bool(denoise),
    }
    if dimensions:
        meta["dimensions"] = _dimensions(pooled, bead_coef, images, space_grid, gammas,
                                         (gy, gx), shape)
    if pooled.fields is not None:  # each image's share of its own field (shrink.py)
        meta["field_share"] = [round(float(v), 4) for v in pooled.fields.share()]
        meta["field_downweighted"] = [int(np.sum(w < 1.0)) for w in pooled.fields.weights]
    return OperatorFamily(images, space_grid, (gy, gx), shape, gammas, cone,
                            grid_step=float(grid_step), metadata=meta)


def _dimensions(pooled: _Pooled, bead_coef: list[tuple], images: np.ndarray,
                space: np.ndarray, gammas: np.ndarray, grid, shape) -> dict:
    """The choice of the family's few dimensions (:func:`.dimensions.choose_dimensions`):
    each image's inlier beads as a clicked bead is seen, its raw patch projected on the
    final basis."""
    inl = pooled.basis.inliers
    flat = images.reshape(len(images), -1)
    raw = np.linalg.lstsq(flat.T, pooled.psf[inl].reshape(int(np.count_nonzero(inl)), -1).T,
                          rcond=None)[0].T
    owner, sd = pooled.owner[inl], pooled.sd[inl]
    beads = [Beads(centers, raw[owner == k], sd[owner == k]) if len(centers) else None
             for k, (centers, _) in enumerate(bead_coef)]
    fields = family_fields(space, gammas)
    # the beads' noise as measured on them, in the choice as when an image is identified
    factor = noise_factor(fields, beads, grid, flat @ flat.T)
    beads = [None if b is None else replace(b, sd=b.sd * factor) for b in beads]
    out = choose_dimensions(fields, beads, grid, shape, flat @ flat.T)
    out["noise_factor"] = round(factor, 4)
    # the family's own error from its beads' noise alone: the band's lower floor
    out["floor"] = (None if pooled.fields is None
                    else float(np.median(pooled.fields.relative_noise())))
    return out


def max_space(n_images: int, n_psf: int | None = None, *,
              psf_radius: float | None = None) -> int | None:
    """The most spatial maps ``J`` a family of ``n_images`` images can have: one per map
    ``alpha_ik``, ``K x I``. Without ``I`` (chosen from the beads), ``I`` is at most the
    pixels of a patch's window (``psf_radius`` given), else None (no bound known)."""
    if n_psf is None and psf_radius is not None:
        size = patch_size(float(psf_radius))
        n_psf = int(np.count_nonzero(radial_distance(size) < R_EXT_FACTOR * float(psf_radius)))
    return None if n_psf is None else int(n_images) * int(n_psf)


@blas_threads
def iter_estimate_family(
    images: Sequence[np.ndarray | Callable[[], np.ndarray]] | np.ndarray,
    *,
    psf_radius: float,
    n_psf: int | None = None,
    n_space: int | None = None,
    client=None,
    threshold: float = 8.0,
    grid_step: float = 32.0,
    refine: bool = False,
    denoise: bool = True,
    holdout: float | None = 0.2,
    chunk: int = 8,
) -> Generator[Progress, None, OperatorFamily]:
    """Learn the subspace of a microscope's operators from images of beads.

    Parameters
    ----------
    images : list of ndarray (H, W) or of zero-argument loaders, or ndarray (K, H, W)
        One image per condition, all of one shape. Loaders are called inside the tasks,
        so that no process holds the whole stack.
    psf_radius : float
        PSF radius, pixels (one patch size for every image).
    n_psf, n_space : int, optional
        ``I`` and ``J``; default: the Gavish-Donoho rule on the patches whitened by their
        noise (capped at 12) and on the maps (capped at 16).
    client : dask.distributed.Client, optional
        Run the per-image tasks on this cluster; default: dask's local threaded scheduler.
    threshold : float
        Detection threshold, noise standard deviations of the filtered image.
    grid_step : float
        Spacing (pixels) of the coarse grid the maps ``a_j`` live on.
    refine : bool
        Refit each ``Gamma_k`` to its own beads' coefficients through the ``a_j`` (step
        8 of the module's notes) instead of projecting its maps.
    denoise : bool
        Learn the basis from Wiener-filtered patches and refit its images to the raw
        patches (as :func:`~napari_psfspace.core.model.estimate.estimate_operator`).
    holdout : float or None
        Fraction of each image's beads held out: they measure each image's operator and
        choose its blend with the image's own estimate
        (:mod:`~napari_psfspace.core.family.choice`); None: the paper's model, the
        family's operators alone, and no held-out figures.
    chunk : int
        Images per dask task.

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    OperatorFamily
    """
    t0 = time.perf_counter()
    items, grid_step, options = _checked(images, psf_radius, n_psf, n_space, client, grid_step,
                                         refine, denoise)
    found = yield from extract_patches(items, float(psf_radius), threshold=threshold,
                                       client=client, chunk=chunk)
    shape, used, skipped = usable_images(found, grid_step, n_psf)
    # the error of each image's operator on beads of its own (about a fifth, spread over
    # the field) that the family never saw; each judged image's own estimate from all its
    # beads (blended in where the judgement says so) is started now, beside the size rule
    held, train = hold_out(used, shape, holdout)
    early_judged = sorted(held)
    own_early = _start_own_estimates(used, early_judged, shape, grid_step, denoise, client)
    n_psf, sizes_meta = family_sizes(used, n_psf, n_space, len(found), min_beads=MIN_BEADS_TPS)
    options["n_psf"] = n_psf
    heldout = None
    choices: list[Choice] = []
    # the family from every bead does not depend on the held-out judgement (only which
    # images blend in their own estimate does): it is learnt beside the judgement's tasks
    import dask

    final = dask.delayed(_learn)(used, shape, dimensions=True, **options)
    sub = None
    own_all: dict = {}  # the images' own estimates from all their beads, by index
    if holdout:
        sub, choices, heldout, own_all = yield from _judge(
            used, train, held, early_judged, own_early, final, shape, options, client)
    sub = yield from _blend_own(sub, final, used, choices, own_all, shape, grid_step, denoise,
                                client)
    sub.metadata.update(sizes_meta)
    sub.metadata.update({
        "images": [f.index for f in used], "skipped": {str(k): v for k, v in skipped.items()},
        "beads_per_image": [int(f.n_beads) for f in used], "psf_radius": float(psf_radius),
        "heldout": heldout, "operator_choice": [c.to_dict() for c in choices] or None,
        "seconds": round(time.perf_counter() - t0, 3)})
    yield Progress("subspace", 1.0, f"I = {sub.n_psf}, J = {sub.n_space} from {len(used)} "
                                    "images")
    return sub


def _checked(images, psf_radius, n_psf, n_space, client, grid_step, refine, denoise):
    """The images as a list, and the options of the family; one clear line for a bad value
    before any work."""
    items = _items(images)
    if len(items) < 2:
        raise ValueError(f"`images` must hold at least 2 images to learn a family, got "
                         f"{len(items)}: learn one operator with estimate_operator instead")
    check_positive(psf_radius, "psf_radius")  # pixels
    if client is not None and not (callable(getattr(client, "compute", None))
                                   and callable(getattr(client, "gather", None))):
        raise ValueError(f"`client` must be a dask.distributed Client (with compute and "
                         f"gather) or None, got {client!r}")
    for name, v in (("n_psf", n_psf), ("n_space", n_space)):
        if v is not None and (int(v) != v or v < 1):
            raise ValueError(f"`{name}` must be a positive integer or None, got {v!r}")
    grid_step = check_positive(grid_step, "grid_step")  # against the shape once read
    most = max_space(len(items), n_psf)
    if n_space is not None and most is not None and n_space > most:
        raise ValueError(f"`n_space` = {n_space} is more spatial maps than {len(items)} images "
                         f"of {int(n_psf)} PSFs give: at most {most}")
    options = {"n_psf": n_psf, "n_space": n_space, "grid_step": grid_step, "refine": refine,
               "denoise": denoise}
    return items, grid_step, options


def _start_own_estimates(used, early_judged, shape, grid_step, denoise, client):
    """The judged images' own estimates from all their beads, started now on a thread of
    their own (blended in where the judgement says so)."""
    import dask

    early = ThreadPoolExecutor(1)
    own_early = early.submit(compute_tasks, [
        dask.delayed(own_estimate)(used[i].patches, shape, grid_step=grid_step,
                                   denoise=denoise) for i in early_judged], client)
    early.shutdown(wait=False)  # its thread ends with the task
    return own_early


def _blend_own(sub, final, used, choices, own_all, shape, grid_step, denoise, client):
    """Each image the judgement blends its own estimate into gets it (from all its beads:
    learnt early beside the judgement, or now, with the family from every bead where that
    was not learnt yet) and its weight."""
    import dask

    blended = [i for i, c in enumerate(choices) if c.weight < 1.0]
    missing = [i for i in blended if i not in own_all]
    tasks = [dask.delayed(own_estimate)(used[i].patches, shape, grid_step=grid_step,
                                        denoise=denoise) for i in missing]
    if sub is None:
        tasks.insert(0, final)
    done = yield from wait_with_progress(
        lambda: compute_tasks(tasks, client) if tasks else [],
        Progress("subspace", 0.8, f"learning from the {len(used)} images"))
    if sub is None:
        sub, *done = done
    own_all.update(zip(missing, done, strict=True))
    owns = [own_all[i] for i in blended]
    weights = np.ones(len(used))
    for i, own in zip(blended, owns, strict=True):
        if own is not None:
            sub.own[i] = own
            weights[i] = choices[i].weight
    sub.family_weights = weights
    return sub


def _judge(used, train, held, early_judged, own_early, final, shape, options, client):
    """The family without the held-out beads, each judged image's own estimate from the
    same beads and the judgement between them on the held-out beads, all beside the
    family's choice of dimensions (the longest task), as dask tasks (threads, or the
    cluster's workers): the family from every bead where it was learnt beside them, each
    image's choice, its held-out figures and the own estimates from all beads."""
    import dask

    grid_step, denoise, n_psf = options["grid_step"], options["denoise"], options["n_psf"]
    sub, own_all = None, {}
    judged = list(early_judged)
    if sum(f.n_beads for f in train) < min_beads_for(int(n_psf)):
        # too few beads left to learn the family without the held-out ones: no
        # judgement; every image keeps the family (the paper's model)
        held, judged = {}, []
    # the family without the held-out beads, each image's own estimate from the same
    # beads and the judgement between them on the held-out beads: all beside the
    # family's choice of dimensions (the longest task), as dask tasks (threads, or
    # the cluster's workers)
    trained = dask.delayed(_learn)(train, shape, **options)
    # judged on their held-out beads only: the operators right there alone
    own_train = {i: dask.delayed(own_estimate)(train[i].patches, shape,
                                               grid_step=grid_step, denoise=denoise,
                                               n_image=used[i].n_beads,
                                               at=held[i].centers)
                 for i in judged}
    tasks = [dask.delayed(choose)(trained, i, own_train.get(i), held.get(i))
             for i in range(len(used))]
    if held:
        sub, *choices = yield from wait_with_progress(
            lambda: compute_first(final, tasks, client),
            Progress("held-out", 0.6, "learning with and without the held-out beads"))
        own_all = dict(zip(early_judged, (yield from wait_with_progress(
            own_early.result, Progress("held-out", 0.7, "own estimates from all beads"))),
            strict=True))
    else:  # no judgement: every image keeps the family
        choices = [choose(None, i, None, None) for i in range(len(used))]
    yield Progress("held-out", 0.7, f"family and own estimates learnt without the "
                                    f"held-out beads of {len(held)} images")
    heldout = [c.kept.summary() if c.kept is not None else {"n_beads": 0}
               for c in choices]
    n_own = sum(c.weight < 1.0 for c in choices)
    yield Progress("held-out", 0.8, f"held-out beads of {len(held)} images judged; "
                                    f"{n_own} blend in their own estimate")
    return sub, choices, heldout, own_all


estimate_family = drained(iter_estimate_family, "estimate_family")


def __getattr__(name: str):
    """Old names of the learning (deprecated)."""
    from ..common.deprecate import module_getattr

    return module_getattr(__name__, {
        "estimate_subspace": ("estimate_family", lambda: estimate_family),
        "iter_estimate_subspace": ("iter_estimate_family", lambda: iter_estimate_family)})(name)
