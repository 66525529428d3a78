"""The richest field model a handful of beads supports (1 to :data:`FEW_BEADS` beads).

Thin-plate splines and the PCA's outlier test are made for many beads; an image with
five usable beads still holds information on how the PSF changes over the field, but it
must be weighed against the noise of so few examples. Candidate models, from the
simplest:

* **shift-invariant**: one PSF for the whole field, the mean of the beads' normalised
  patches;
* **affine, I = 2 or 3** (from :data:`FIELD_MIN_BEADS` beads): a basis of ``I`` PSFs
  (PCA of the patches) whose coefficients vary as planes over the field (the smoothest
  field there is: the thin-plate spline's null space), kept inside the cone of the
  observed coefficients;
* **thin-plate, I = 2 or 3** (from :data:`MIN_THIN_PLATE` beads): the same basis with
  thin-plate splines whose smoothing is chosen by leaving one bead out (a field that
  can bend: the PSF sharp in the centre, defocused towards the corners).

Leave-one-bead-out chooses: each bead in turn is predicted by the model learnt from the
others (basis and smoothing included), and the candidate with the lowest mean relative
squared error wins; a richer candidate must beat a simpler one by 1 %. Below
:data:`FIELD_MIN_BEADS` beads (the fewest a model is judged on held-out beads from, as in
3D) the field is not mapped: the model is one PSF, and says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..beads.detect import NoBeadsError
from ..beads.patches import Patches
from .cone import Cone, reduce_cone
from .field import assemble_operator
from .heldout import HeldoutResiduals, heldout_residuals
from .operator import ProductConvolution
from .pca import min_beads_for, orient
from .tps import ThinPlateSpline

#: Up to this many usable beads, :func:`fit_few_beads` chooses the field model.
FEW_BEADS = 10
#: Largest basis of the affine candidates.
MAX_FEW_PSF = 3
#: Fewest beads a field that varies is learnt from: the fewest a basis is learnt and
#: judged on held-out beads from (the 3D model's floor too). Four beads leave three to
#: fit a plane through each left out: no evidence for a map, only for a mean.
FIELD_MIN_BEADS = min_beads_for(1)
#: What the field maps say of a model of fewer beads.
TOO_FEW = "one PSF: too few beads to map the field"


@dataclass
class FewBeadsFit:
    """Result of :func:`fit_few_beads`.

    Attributes
    ----------
    operator : ProductConvolution
    field_model : str
        "shift-invariant", "affine" or "thin-plate".
    n_psf : int
    reason : str
        Why this model, in words (for the CLI, the widget and the metadata).
    basis : ndarray of shape (I, P, P)
        The basis before any ``basis_filter`` (what ``coefficients`` refer to).
    coefficients : ndarray of shape (M, I)
        The beads' coefficients.
    cone : Cone
        Their cone.
    loo_errors : dict
        Candidate name -> leave-one-bead-out relative squared error (empty with fewer
        than 3 beads).
    heldout : HeldoutResiduals or None
        Each bead's residual under the chosen model learnt without it.
    """

    operator: ProductConvolution
    field_model: str
    n_psf: int
    reason: str
    basis: np.ndarray
    coefficients: np.ndarray
    cone: Cone
    loo_errors: dict = field(default_factory=dict)
    heldout: HeldoutResiduals | None = None

    def metadata(self) -> dict:
        """JSON-ready record for the operator's metadata."""
        return {"field_model": self.field_model, "field_model_reason": self.reason,
                "loo_errors": {k: float(v) for k, v in self.loo_errors.items()}}


def _affine(positions: np.ndarray, values: np.ndarray, scale: float):
    """Least-squares planes ``v = a + b y + c x`` through the samples; returns the field."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    centre = pos.mean(axis=0)
    design = np.column_stack([np.ones(len(pos)), (pos - centre) / scale])
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)

    def field_at(nodes):
        z = (np.asarray(nodes, dtype=np.float64).reshape(-1, 2) - centre) / scale
        return np.column_stack([np.ones(len(z)), z]) @ coef

    return field_at


#: Fewest beads for a thin-plate candidate (leaving one out leaves 5 to fit it).
MIN_THIN_PLATE = 6


def _candidates(n: int, positions: np.ndarray) -> list[tuple[str, int]]:
    """(field model, basis size) pairs ``n`` beads can be fitted with, simplest first:
    one PSF; an affine field of 2-3 PSFs (leaving one bead out must still fit a plane: 4
    beads or more, not all on one line; chosen unasked only from :data:`FIELD_MIN_BEADS`
    beads); thin-plate splines with smoothing chosen by leaving one
    out (:data:`MIN_THIN_PLATE` beads or more)."""
    spread = n >= 4 and np.linalg.matrix_rank(np.column_stack([np.ones(n), positions])) == 3
    top = min(MAX_FEW_PSF, n - 2) if spread else 1
    out = [("shift-invariant", 1)] + [("affine", i) for i in range(2, top + 1)]
    if spread and n >= MIN_THIN_PLATE:
        out += [("thin-plate", i) for i in range(2, top + 1)]
    return out


def _model(psf: np.ndarray, positions: np.ndarray, kind: str, n_psf: int,
           support: np.ndarray, scale: float):
    """Basis (I, P, P), coefficients (M, I) and field of a candidate learnt from ``psf``."""
    p = psf.shape[-1]
    if n_psf == 1:
        mean = psf.mean(axis=0)
        basis = mean[None] / max(float(mean.sum()), 1e-300)
        beta = np.ones((len(psf), 1))

        def const(nodes):
            return np.ones((len(np.asarray(nodes).reshape(-1, 2)), 1))

        return basis, beta, const
    x = psf[:, support]
    xn = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)
    _, _, vt = np.linalg.svd(xn, full_matrices=False)
    vt = orient(vt[:n_psf])
    basis = np.zeros((n_psf, p, p))
    basis[:, support] = vt
    beta = x @ vt.T
    if kind == "thin-plate":  # smoothing per coefficient by leave-one-out
        return basis, beta, ThinPlateSpline(positions, beta, scale=scale)
    return basis, beta, _affine(positions, beta, scale)


@dataclass(frozen=True)
class _OnePsf:
    """The model's PSF at a left-out bead, as :func:`heldout_residuals` reads a model."""

    psf: np.ndarray

    @property
    def psf_size(self) -> int:
        return self.psf.shape[-1]

    def psf_at(self, y: float, x: float) -> np.ndarray:
        return self.psf


def _predict(basis, beta, field_at, position) -> np.ndarray:
    """The model's sum-1 PSF at one position, kept in the cone of ``beta``."""
    coef = reduce_cone(beta).project(np.atleast_2d(field_at(position[None])))[0]
    psf = np.tensordot(coef, basis, axes=1)
    total = float(psf.sum())
    if total <= 1e-12:
        psf = np.tensordot(beta.mean(axis=0), basis, axes=1)
        total = float(psf.sum())
    return psf / total


def fit_few_beads(
    patches: Patches,
    shape: tuple[int, int],
    *,
    n_psf: int | None = None,
    support: np.ndarray | None = None,
    grid_step: float = 32.0,
    metadata: dict | None = None,
    basis_filter=None,
) -> FewBeadsFit:
    """Choose and fit the field model of 1 to :data:`FEW_BEADS` beads (see module doc).

    Parameters
    ----------
    patches : Patches
        The usable beads' patches (sum-1 ``psf``).
    shape : tuple of int
        Image shape.
    n_psf : int, optional
        A fixed basis size (1: shift-invariant; 2 or 3: the affine or thin-plate field
        that leaving one bead out prefers), instead of the leave-one-bead-out choice.
    support : ndarray of shape (P, P), bool, optional
        Pixels the windowed patches can reach (default: all).
    grid_step, metadata, basis_filter
        As in :func:`~napari_psfspace.core.model.field.assemble_operator`.

    Returns
    -------
    FewBeadsFit

    Raises
    ------
    NoBeadsError
        No patch, or a fixed ``n_psf`` the beads cannot support.
    """
    n = len(patches)
    if n == 0:
        raise NoBeadsError("No usable bead to learn a PSF from.")
    psf = np.asarray(patches.psf, dtype=np.float64)
    pos = np.asarray(patches.centers, dtype=np.float64)
    mask = np.ones(psf.shape[1:], bool) if support is None else np.asarray(support, bool)
    scale = 0.5 * float(np.hypot(*shape))
    supported = _candidates(n, pos)
    sizes = sorted({size for _, size in supported})
    if n_psf is not None and n_psf not in sizes:
        raise NoBeadsError(
            f"Too few usable beads for a basis of `n_psf` = {n_psf}: {n} bead(s) support a "
            f"basis of at most {max(sizes)} (a field that varies needs the basis size "
            f"plus 2 beads, not all on one line, and at most {MAX_FEW_PSF} PSFs below "
            f"{FEW_BEADS + 1} beads). Lower `n_psf`, or image a denser bead slide.")
    cands = supported if n_psf is None else [c for c in supported if c[1] == n_psf]

    loo: dict[str, float] = {}
    residuals = {}
    if n >= 3:
        norm2 = np.mean([(p[mask] ** 2).sum() for p in psf])
        for kind, size in cands:
            errs, res = [], []
            for m in range(n):
                others = np.arange(n) != m
                basis, beta, field_at = _model(psf[others], pos[others], kind, size, mask,
                                               scale)
                pred = _predict(basis, beta, field_at, pos[m])
                errs.append(float(((psf[m] - pred)[mask] ** 2).sum()))
                res.append(heldout_residuals(_OnePsf(pred), patches.subset([m])))
            loo[_name(kind, size)] = float(np.mean(errs) / norm2)
            residuals[(kind, size)] = HeldoutResiduals(
                np.concatenate([r.positions for r in res]),
                np.concatenate([r.residual for r in res]),
                np.concatenate([r.noise_floor for r in res]))
        # below FIELD_MIN_BEADS every candidate is scored (the reason reports it) but
        # only one PSF is chosen unasked: a map through three beads at a time is no
        # evidence of the field
        allowed = [c for c in cands
                   if n_psf is not None or c[1] == 1 or n >= FIELD_MIN_BEADS]
        best = min(loo[_name(*c)] for c in allowed)
        chosen = next(c for c in allowed if loo[_name(*c)] <= 1.01 * best)
    else:
        chosen = cands[0]
    kind, size = chosen
    basis, beta, field_at = _model(psf, pos, kind, size, mask, scale)
    # the paper's cone: a few beads' held-out predictions cannot judge where it is needed
    op, cone = assemble_operator(basis, beta, field_at, shape, grid_step=grid_step,
                                 metadata=metadata, basis_filter=basis_filter,
                                 constraint="cone")
    reason = _reason(n, chosen, loo, n_psf)
    return FewBeadsFit(op, kind, size, reason, basis, beta, cone, loo,
                       residuals.get(chosen))


def one_psf_note(metadata: dict) -> str | None:
    """What a model's field maps say where it is one PSF for the whole field: "one PSF:
    too few beads to map the field" below :data:`FIELD_MIN_BEADS` beads, else "one PSF
    for the whole field"; None for a model that varies."""
    if metadata.get("field_model") != "shift-invariant" and metadata.get("n_psf", 0) != 1:
        return None
    used = metadata.get("n_beads_used")
    if used is not None and used < FIELD_MIN_BEADS:
        return TOO_FEW
    return "one PSF for the whole field"


def _name(kind: str, size: int) -> str:
    return kind if size == 1 else f"{kind}, I={size}"


def _reason(n: int, chosen: tuple[str, int], loo: dict, n_psf: int | None) -> str:
    """Why this field model, in words (the model itself is stated by the caller)."""
    beads = f"{n} usable bead{'s' if n != 1 else ''}"
    kind, size = chosen
    errs = ", ".join(f"{k} {v:.3g}" for k, v in loo.items())
    if n_psf is not None:
        return (f"{beads}; the basis size was fixed (`n_psf` = {n_psf})"
                + (f"; leave-one-bead-out error: {errs}." if errs else "."))
    if n < FIELD_MIN_BEADS:
        text = (f"{beads}, fewer than {FIELD_MIN_BEADS}: {TOO_FEW} (a field that varies is "
                f"learnt and judged on held-out beads from {FIELD_MIN_BEADS}). Image more "
                "beads to see it vary.")
        one = loo.get("shift-invariant")
        better = {k: v for k, v in loo.items() if one is not None and v < one}
        if better:
            name = min(better, key=better.get)
            text += (f" Leaving one bead out, {name} predicted them better ({errs}): "
                     f"`n_psf` = {name.rsplit('=', 1)[-1]} asks for it.")
        return text
    if size == 1 and len(loo) == 1:
        return (f"{beads}, all on one line: {TOO_FEW} (a field that varies needs beads "
                f"not on one line; leave-one-bead-out error {errs}). Image more beads to "
                "see it vary.")
    if size == 1:
        return (f"{beads}: no model that varies over the field predicted a left-out bead "
                f"better (leave-one-bead-out error: {errs}). Image more beads to resolve "
                "the variation.")
    return (f"{beads}: {size} PSFs with a {kind} field, the model that predicted left-out "
            f"beads best (leave-one-bead-out error: {errs}).")
