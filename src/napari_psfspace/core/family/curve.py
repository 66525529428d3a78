"""A family along one curve: its fields as a polynomial in one condition that varies as
a plane over the field.

A microscope's operators change with a condition (the focus above all) that a tilted
slide makes vary across the field. The PSF is not linear in the focus: near focus it
changes as its square. So instead of :mod:`.dimensions`' straight directions, a
family's fields are modelled as

    F(x) = sum_d t(x)^d C_d(x) + R(x),    t(x) = theta_0 + theta_1 u(x) + theta_2 v(x),

``u``, ``v`` the scaled row and column (-0.5 to 0.5 across the image), ``C_d`` (``d``
up to :data:`DEGREE`, or another of :data:`DEGREES` where chosen) fields learnt from
the family, ``theta`` three numbers per image
(its condition at the centre and its slopes across the field along rows and columns),
``R`` the family's miss as in :mod:`.coordinates`. Given every image's ``theta`` the
``C_d`` are exact least squares node by node, so learning moves the ``theta`` alone,
the ``C_d`` eliminated (variable projection, Levenberg-Marquardt): a near-focus family
whose straight directions need many coordinates is three numbers an image.

An image's ``theta`` and its beads' amplitudes are identified from its beads by
Gauss-Newton (:meth:`Curve.fit`), with the family's spread of ``theta`` as their prior;
the posterior covariance, the kriging of the miss, the spread and the bead check are
then those of the model linearised at the estimate (:meth:`Curve.linearized`, a
:class:`~.coordinates.Model` whose three coordinates are ``theta`` whitened by that
prior). :mod:`.dimensions` keeps the curve only where it identifies the family's own
images, each left out, better than its straight directions do.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .coordinates import CoordinateFit, Model, bilinear, design, identify_field, whitener
from .miss import miss_model

#: Degree of the polynomial in the condition (2: the PSF's change near focus is
#: quadratic in it); a family's ``theta`` are first learnt with it.
DEGREE = 2
#: Degrees a family's curve is judged with (:mod:`.dimensions`), each one's ``theta``
#: learnt from :data:`DEGREE`'s: away from focus the PSF's change is not quadratic, and
#: a cubic follows it where the family's images say so.
DEGREES = (2, 3)
#: Fewest images a curve is learnt from: ``DEGREE + 1`` fields at each node, and two more
#: to judge them (a higher degree of :data:`DEGREES` is judged only with as many more).
MIN_IMAGES = DEGREE + 3
#: Steps of the learning at most; it stops once the squared residual falls by less than
#: :data:`LEARN_TOL` of itself.
LEARN_ITERATIONS = 50
LEARN_TOL = 1e-6
#: Gauss-Newton steps of one field's ``theta`` given the ``C_d`` (:func:`theta_of`: a
#: field left out, fitted by the others' curve).
THETA_STEPS = 10
#: The prior of an image's ``theta``: the family's spread of them, its standard
#: deviation scaled by this (images beyond the conditions learnt are expected).
PRIOR_SCALE = 2.0
#: Starts of the identification: the family's images' ``theta`` of least objective.
N_STARTS = 3
#: Gauss-Newton steps of the identification at most; it stops once ``eta`` (``theta``
#: in units of its prior's spread) changes by less than :data:`FIT_TOL`.
FIT_STEPS = 50
FIT_TOL = 1e-4


def plane_design(nodes: np.ndarray, shape) -> np.ndarray:
    """``[1, u, v]`` (G, 3) at ``nodes`` (G, 2), ``u``, ``v`` the scaled row and column
    (-0.5 to 0.5 across an image of ``shape``)."""
    rel = np.asarray(nodes, np.float64).reshape(-1, 2) / np.maximum(
        np.asarray(shape, np.float64) - 1, 1) - 0.5
    return np.column_stack([np.ones(len(rel)), rel])


def _powers(t: np.ndarray, degree: int) -> np.ndarray:
    return np.stack([t ** d for d in range(degree + 1)], axis=-1)


def _slopes(t: np.ndarray, degree: int) -> np.ndarray:
    """d/dt of :func:`_powers`."""
    return np.stack([d * t ** (d - 1) if d else np.zeros_like(t)
                     for d in range(degree + 1)], axis=-1)


def fields_given(fields_w: np.ndarray, t: np.ndarray, degree: int) -> np.ndarray:
    """The ``C_d`` (G, D + 1, I) of least squares, node by node, of fields (K, G, I) given
    each image's condition at each node ``t`` (K, G)."""
    x = _powers(np.asarray(t).T, degree)  # (G, K, D + 1)
    xt = np.swapaxes(x, 1, 2)
    xtx = xt @ x
    ridge = 1e-12 * np.trace(xtx, axis1=1, axis2=2)[:, None, None] * np.eye(degree + 1)
    return np.linalg.solve(xtx + ridge, xt @ np.swapaxes(fields_w, 0, 1))


def theta_of(field_w: np.ndarray, coef_w: np.ndarray, planes: np.ndarray,
             theta: np.ndarray, *, steps: int = THETA_STEPS) -> np.ndarray:
    """One field's ``theta`` (3,) of least squares given the ``C_d`` (G, D + 1, I), by
    Gauss-Newton from ``theta`` (a step that does not lower the residual is halved)."""
    degree = coef_w.shape[1] - 1

    def fit(th):
        return np.einsum("gd,gdi->gi", _powers(planes @ th, degree), coef_w)

    th = np.asarray(theta, np.float64).copy()
    res = field_w - fit(th)
    cost = float((res * res).sum())
    for _ in range(int(steps)):
        t = planes @ th
        tangent = np.einsum("gd,gdi->gi", _slopes(t, degree), coef_w)
        # the normal equations of the Jacobian tangent (G, I) times [1, u, v] (G, 3)
        jtj = np.einsum("g,ga,gb->ab", (tangent * tangent).sum(axis=1), planes, planes)
        jtr = np.einsum("g,ga->a", (tangent * res).sum(axis=1), planes)
        step = np.linalg.lstsq(jtj, jtr, rcond=None)[0]
        for _ in range(10):
            new = th + step
            res_new = field_w - fit(new)
            cost_new = float((res_new * res_new).sum())
            if cost_new <= cost:
                th, res, cost = new, res_new, cost_new
                break
            step = step / 2
        else:
            break
    return th


@dataclass
class Curve:
    """A family's fields along one curve (see the module's notes).

    Attributes
    ----------
    frame : Model
        The grid, image shape, Gram matrix and the family's miss (its ``mean`` the field
        at ``theta = 0``, no directions).
    coef : ndarray of shape (D + 1, G, I)
        ``C_d``.
    thetas : ndarray of shape (K, 3)
        The family's images' ``theta``.
    prior_mean : ndarray of shape (3,)
    prior_factor : ndarray of shape (3, 3)
        ``S``, lower triangular: ``theta = prior_mean + S eta``, ``eta`` of unit normal
        prior.
    miss_factor : float
        ``F``: how much of the family's miss a clicked bead's residual is weighed with
        (:meth:`bead_whiteners`).
    """

    frame: Model
    coef: np.ndarray
    thetas: np.ndarray
    prior_mean: np.ndarray
    prior_factor: np.ndarray
    miss_factor: float = 1.0

    @property
    def degree(self) -> int:
        return int(len(self.coef) - 1)

    @property
    def nodes(self) -> np.ndarray:
        return self.frame.nodes

    @property
    def central(self) -> np.ndarray:
        return self.frame.central

    def theta(self, eta: np.ndarray) -> np.ndarray:
        """``theta`` (3,) of whitened coordinates ``eta`` (3,)."""
        return self.prior_mean + self.prior_factor @ np.asarray(eta, np.float64)

    def eta(self, theta: np.ndarray) -> np.ndarray:
        """The whitened coordinates (3,) of ``theta`` (3,)."""
        return np.linalg.solve(self.prior_factor,
                               np.asarray(theta, np.float64) - self.prior_mean)

    def _at(self, coef: np.ndarray, planes: np.ndarray, eta: np.ndarray):
        """The field (P, I) and its derivatives along ``eta`` (3, P, I) given ``C_d``
        (P, D + 1, I) and ``[1, u, v]`` (P, 3) at the same points."""
        t = planes @ self.theta(eta)
        field = np.einsum("pd,dpi->pi", _powers(t, self.degree), coef)
        tangent = np.einsum("pd,dpi->pi", _slopes(t, self.degree), coef)
        # d t / d eta_k at each point: [1, u, v] times the prior factor's column k
        return field, (planes @ self.prior_factor).T[:, :, None] * tangent[None]

    def linearized(self, eta: np.ndarray) -> Model:
        """The linear model about ``eta`` (its coordinates the whitened ``eta``, unit
        prior variances): ``field(eta)`` is the curve's field there."""
        planes = plane_design(self.nodes, self.frame.shape)
        field, dirs = self._at(self.coef, planes, eta)
        mean = field - np.tensordot(np.asarray(eta, np.float64), dirs, axes=1)
        return replace(self.frame, mean=mean, directions=dirs, variances=np.ones(3))

    def _at_beads(self, centers: np.ndarray, white: np.ndarray):
        """A function of ``eta``: the curve's field at ``centers`` (P, I) and its
        derivatives along ``eta`` (P, I, 3), both times the basis's whitener ``white``
        (I, I) (the field at the nodes around the beads, bilinear between, as the
        operator interpolates its PSFs)."""
        w = bilinear(self.frame.grid, centers)
        used = np.flatnonzero(np.any(w != 0, axis=0))
        w = w[:, used]
        coef = self.coef[:, used] @ white.T  # the field is linear in the C_d
        planes = plane_design(self.nodes[used], self.frame.shape)

        def at(eta):
            field, dirs = self._at(coef, planes, eta)
            return w @ field, np.einsum("pn,jni->pij", w, dirs)

        return at

    def fit(self, c: np.ndarray, sd: np.ndarray, centers: np.ndarray, *,
            amplitude_range: tuple[float, float] = (0.5, 2.0),
            start: np.ndarray | None = None):
        """An image's ``eta`` from its beads: ``(model, fit)``, the linear model about
        the estimate (:meth:`linearized`) and its :class:`~.coordinates.CoordinateFit`
        there (``fit.z`` is ``eta``).

        Generalised least squares: each bead's residual about the curve is its noise
        and the family's miss there (:meth:`bead_whiteners`), so that the three numbers
        do not bend to fit what the curve cannot hold; the miss is kriged from the
        residuals afterwards. Gauss-Newton on ``eta`` and the amplitudes together (the
        amplitudes kept in ``amplitude_range``; a step that raises the posterior
        objective is halved), from the :data:`N_STARTS` family images' ``theta`` that
        explain the beads best (or from ``start`` alone, an ``eta``); the estimate of
        least objective is kept.
        """
        c = np.asarray(c, np.float64)
        sd = np.asarray(sd, np.float64).reshape(-1)
        good = np.isfinite(sd) & (sd > 0)
        sd = np.where(good, sd, np.median(sd[good]) if good.any() else 1.0)
        centers = np.asarray(centers, np.float64).reshape(-1, 2)
        n_p = len(c)
        white = whitener(self.frame.gram)
        at = self._at_beads(centers, white)
        scale = self.bead_scales(sd, centers)  # (P,): each bead's whitener, a multiple of I
        cw = c @ white.T
        cv = cw * scale[:, None]  # the beads' coefficients, bead-whitened
        lo, hi = amplitude_range

        # bead whitener times basis whitener, the rows of one bead's whitened residual
        inv_white = white[None] * scale[:, None, None]

        def state(eta, g=None):
            """The bead-whitened fit (P, I) and its derivatives along ``eta``
            (P, I, 3), the amplitudes (fitted when None) and the objective."""
            field, dirs = at(eta)
            fw = field * scale[:, None]
            if g is None:
                mm = np.maximum((fw * fw).sum(axis=1), 1e-300)
                g = np.clip((fw * cv).sum(axis=1) / mm, lo, hi)
            res = cv - g[:, None] * fw
            return (fw, dirs * scale[:, None, None]), g, float(
                (res * res).sum() + np.dot(eta, eta))

        def solve(eta):
            (fw, dw), g, cost = state(eta)
            for _ in range(FIT_STEPS):
                res = cv - g[:, None] * fw
                jac = np.zeros((n_p, cw.shape[1], 3 + n_p))
                jac[:, :, :3] = dw * g[:, None, None]
                jac[np.arange(n_p), :, 3 + np.arange(n_p)] = fw
                # the beads' rows and the prior's (unit normal on eta), by least squares
                jac = np.vstack([jac.reshape(-1, 3 + n_p), np.eye(3, 3 + n_p)])
                step = np.linalg.lstsq(jac, np.r_[res.reshape(-1), -eta], rcond=None)[0]
                for _ in range(20):
                    new_eta = eta + step[:3]
                    new_g = np.clip(g + step[3:], lo, hi)
                    new_w, _, new_cost = state(new_eta, new_g)
                    if new_cost <= cost:
                        break
                    step = step / 2
                else:
                    break
                done = float(np.max(np.abs(new_eta - eta))) < FIT_TOL
                eta, g, (fw, dw), cost = new_eta, new_g, new_w, new_cost
                if done:
                    break
            return cost, eta, g

        starts = ([self.eta(th) for th in self.thetas] if start is None
                  else [np.asarray(start, np.float64)])
        costs = [state(e)[2] for e in starts]
        best = min((solve(starts[int(i)]) for i in np.argsort(costs)[:N_STARTS]),
                   key=lambda found: found[0])
        _, eta, g = best
        model = self.linearized(eta)
        base, a = design(model, centers)
        fitted = base + a @ eta
        rows = np.einsum("pik,pkl->pil", inv_white, a) * g[:, None, None]
        rows = rows.reshape(-1, 3)
        cov = np.linalg.inv(rows.T @ rows + np.eye(3))  # given the amplitudes
        return model, CoordinateFit(eta, cov, g, fitted, c / g[:, None] - fitted, sd / g,
                                    centers)

    def bead_whiteners(self, sd: np.ndarray, centers: np.ndarray) -> np.ndarray:
        """Each bead's whitener (P, I, I) of its whitened coefficients' residual about
        the curve: ``L_p`` with ``L_p^T L_p`` the inverse of its covariance, its noise
        (``sd_p^2``, white) plus the family's miss at it, spread evenly over the
        coefficients (``F s(x_p)^2 trace(W C_R W^T) / I``, ``F`` :attr:`miss_factor`).

        Spread evenly, not as ``C_R``: the family's miss lies mostly along the
        directions its fields differ in, the very ones the three numbers are read from,
        and weighing them down leaves those numbers to the rest (the identification
        benches measure it the worse). ``F`` is chosen with the curve by
        identifying the family's own images, each left out (:mod:`.dimensions`): a
        single bead strays from its image's field by more than that field strays from
        its family's curve (its centring, its background), and the choice measures by
        how much. The miss's correlation between beads is left out, although clicked
        beads often lie within its length: weighed in, it identifies the learning
        curve's images (``bench/bench_identify_curve.py``) the worse."""
        scale = self.bead_scales(sd, centers)
        return np.eye(len(self.frame.gram))[None] * scale[:, None, None]

    def bead_scales(self, sd: np.ndarray, centers: np.ndarray) -> np.ndarray:
        """Each bead's whitener of :meth:`bead_whiteners` as the multiple of the identity
        it is (P,): one over the standard deviation of its residual."""
        white = whitener(self.frame.gram)
        n_i = len(white)
        per = float(np.trace(white @ self.frame.miss_cov @ white.T)) / n_i
        var = np.asarray(sd, np.float64) ** 2 + self.miss_factor * per * self.frame.scale_at(
            centers) ** 2
        return 1.0 / np.sqrt(var)

    def field(self, eta: np.ndarray) -> np.ndarray:
        """The curve's field at the nodes (G, I) at ``eta``."""
        planes = plane_design(self.nodes, self.frame.shape)
        return self._at(self.coef, planes, eta)[0]


def _gauged(thetas: np.ndarray) -> np.ndarray:
    """``theta`` (K, 3) in the gauge of the images' ``theta_0`` of mean 0 and standard
    deviation 1 (``t`` is defined up to an affine map)."""
    s = max(float(thetas[:, 0].std()), 1e-300)
    return np.column_stack([(thetas[:, 0] - thetas[:, 0].mean()) / s, thetas[:, 1:] / s])


def _cost_and_step(fg: np.ndarray, thetas: np.ndarray, planes: np.ndarray, degree: int,
                   damping: float) -> tuple[float, np.ndarray]:
    """The squared residual of the curve given ``theta`` (its ``C_d`` of least squares)
    and the damped Gauss-Newton step of every ``theta`` together (K, 3), of the whitened
    fields node-major ``fg`` (G, K, I), contiguous (each node's K x K algebra a matmul).

    The ``C_d`` are eliminated (variable projection, Kaufman's Jacobian): at node ``g``
    moving ``theta_k`` moves the fit by ``(1 - P_g) e_k s_kg u_g``, ``P_g`` the
    projection on the span of the powers of the ``K`` conditions there, ``s_kg`` the
    fit's derivative in ``t`` and ``u_g = [1, u, v]``; the normal equations are summed
    node by node (3 K unknowns).
    """
    k = fg.shape[1]
    t = planes @ thetas.T  # (G, K)
    x = _powers(t, degree)  # (G, K, D + 1)
    xt = np.ascontiguousarray(np.swapaxes(x, 1, 2))
    xtx = xt @ x
    xtx += 1e-12 * np.trace(xtx, axis1=1, axis2=2)[:, None, None] * np.eye(degree + 1)
    # each node's pseudo-inverse of its powers, once: the C_d and the projection from it
    pinv = np.linalg.inv(xtx) @ xt  # (G, D + 1, K)
    coef = pinv @ fg  # (G, D + 1, I)
    res = fg - x @ coef
    slope = _slopes(t, degree) @ coef  # (G, K, I)
    m = (np.eye(k)[None] - x @ pinv) * (slope @ np.swapaxes(slope, 1, 2))
    pp = (planes[:, :, None] * planes[:, None, :]).reshape(len(planes), 9)
    jtj = (m.reshape(len(m), k * k).T @ pp).reshape(k, k, 3, 3)
    jtj = jtj.transpose(0, 2, 1, 3).reshape(3 * k, 3 * k)
    jtr = (np.einsum("gki,gki->gk", slope, res).T @ planes).reshape(3 * k)
    lhs = jtj + damping * np.diag(np.diag(jtj) + 1e-12 * np.trace(jtj) / (3 * k))
    step = np.linalg.lstsq(lhs, jtr, rcond=None)[0]
    return float(np.einsum("gki,gki->", res, res)), step.reshape(k, 3)


def learn_thetas(fields: np.ndarray, nodes: np.ndarray, shape, gram: np.ndarray, *,
                 degree: int = DEGREE, thetas: np.ndarray | None = None,
                 iterations: int = LEARN_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """The ``C_d`` (D + 1, G, I) and each image's ``theta`` (K, 3) of fields (K, G, I).

    ``theta`` starts from each field's coordinate on the fields' first principal
    direction, fitted as a plane (or from ``thetas``); then every ``theta`` moves
    together by Levenberg-Marquardt on the curve's residual, the ``C_d`` eliminated
    (:func:`_cost_and_step`), at most ``iterations`` steps; it stops once the squared
    residual falls by less than :data:`LEARN_TOL` of itself. The gauge (``t`` up to an
    affine map) is fixed by the images' ``theta_0``: mean 0, standard deviation 1.
    """
    white = whitener(gram).T
    fw = np.asarray(fields, np.float64) @ white
    k, g, n_i = fw.shape
    planes = plane_design(nodes, shape)
    if thetas is None:
        mean = fw.mean(axis=0)
        dev = (fw - mean).reshape(k, -1)
        lead = np.linalg.svd(dev, full_matrices=False)[2][0].reshape(g, n_i)
        x = (lead[None] * planes.T[:, :, None]).reshape(3, -1)
        thetas = np.linalg.lstsq(x.T, dev.T, rcond=None)[0].T
    thetas = _gauged(np.array(thetas, np.float64))
    damping = 1e-3
    fg = np.ascontiguousarray(np.swapaxes(fw, 0, 1))  # (G, K, I), node-major
    cost, step = _cost_and_step(fg, thetas, planes, degree, damping)
    for _ in range(int(iterations)):
        trial = _gauged(thetas + step)
        new_cost, new_step = _cost_and_step(fg, trial, planes, degree, damping)
        if new_cost <= cost:
            done = cost - new_cost <= LEARN_TOL * new_cost
            thetas, cost, step = trial, new_cost, new_step
            damping = max(damping / 3, 1e-9)
            if done:
                break
        else:
            damping *= 10
            if damping > 1e6:
                break
            cost, step = _cost_and_step(fg, thetas, planes, degree, damping)
    coef = fields_given(fw, thetas @ planes.T, degree)
    unwhite = np.linalg.inv(white)
    return np.moveaxis(coef, 1, 0) @ unwhite, thetas


def curve_misses(fields: np.ndarray, thetas: np.ndarray, nodes: np.ndarray, shape,
                 gram: np.ndarray, *, degree: int = DEGREE) -> np.ndarray:
    """Each field (K, G, I) minus its best fit by the curve of the others (their
    ``C_d`` given their ``theta``, its own ``theta`` fitted): the family's miss."""
    white = whitener(gram).T
    fw = np.asarray(fields, np.float64) @ white
    planes = plane_design(nodes, shape)
    out = np.empty_like(fw)
    for j in range(len(fw)):
        rest = np.arange(len(fw)) != j
        coef = fields_given(fw[rest], thetas[rest] @ planes.T, degree)
        start = thetas[rest][int(np.argmin(
            [((fw[j] - np.einsum("gd,gdi->gi", _powers(planes @ th, degree), coef)) ** 2
              ).sum() for th in thetas[rest]]))]
        th = theta_of(fw[j], coef, planes, start)
        out[j] = fw[j] - np.einsum("gd,gdi->gi", _powers(planes @ th, degree), coef)
    return out @ np.linalg.inv(white)


def build_curve(fields: np.ndarray, grid, shape, gram: np.ndarray, *,
                thetas: np.ndarray | None = None, miss: bool = True,
                residuals: np.ndarray | None = None, degree: int = DEGREE,
                miss_factor: float = 1.0) -> Curve:
    """The curve of fields (K, G, I) on ``grid`` of an image of ``shape``: learnt
    (:func:`learn_thetas`; given ``thetas``, only the ``C_d``), with the family's miss
    measured by leaving each field out (:func:`curve_misses`; or modelled from the
    given ``residuals``, (K', G, I); ``miss=False``: none); ``miss_factor``:
    :attr:`Curve.miss_factor`."""
    gy, gx = grid
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    fields = np.asarray(fields, np.float64)
    if thetas is None:
        coef, thetas = learn_thetas(fields, nodes, shape, gram, degree=degree)
    else:
        thetas = np.asarray(thetas, np.float64)
        white = whitener(gram).T
        coef = np.moveaxis(fields_given(fields @ white, thetas @ plane_design(
            nodes, shape).T, degree), 1, 0) @ np.linalg.inv(white)
    n_i = fields.shape[-1]
    cov, length, scale = np.zeros((n_i, n_i)), 1.0, None
    if miss and residuals is None and len(fields) >= MIN_IMAGES:
        residuals = curve_misses(fields, thetas, nodes, shape, gram, degree=degree)
    if miss and residuals is not None:
        cov, length, scale = miss_model(np.asarray(residuals, np.float64), nodes)
    frame = Model((np.asarray(gy), np.asarray(gx)), tuple(shape), coef[0],
                  np.zeros((0, *coef[0].shape)), np.zeros(0), cov, length,
                  np.asarray(gram, np.float64), scale)
    spread = np.cov(thetas.T) * PRIOR_SCALE ** 2
    spread += 1e-9 * max(float(np.trace(spread)), 1e-300) * np.eye(3)
    return Curve(frame, coef, thetas, thetas.mean(axis=0), np.linalg.cholesky(spread),
                 float(miss_factor))


def identify_any(model: Model | Curve, c: np.ndarray, sd: np.ndarray, centers: np.ndarray,
                 *, amplitude_range: tuple[float, float] = (0.5, 2.0), krige: bool = True,
                 spread: bool = True, start: np.ndarray | None = None):
    """:func:`~.coordinates.identify_field` with a family's model of either kind: a
    :class:`Curve` is fitted (:meth:`Curve.fit`, from ``start`` if given) and its linear
    model there used.
    Returns ``(model, (field, spread, fit))``, ``model`` the linear one."""
    if isinstance(model, Curve):
        model, fit = model.fit(c, sd, centers, amplitude_range=amplitude_range, start=start)
    else:
        fit = None
    return model, identify_field(model, c, sd, centers, amplitude_range=amplitude_range,
                                 krige=krige, spread=spread, fit=fit)
