"""A brightness gain per pool, switched on where the pool's equations need it.

Brightness constancy (eq. 8) fails where a surface changes brightness as it
moves: a face driving towards a lamp brightens, a body turning under fixed
lights darkens. A pool of eq. (9) and (15) then reads part of that change as
flow (approach's incoming face came out 3 % fast, the rolling ball half its
radial flow). With a gain beta per pool (per frame, shared by both units'
rows: they see the same surface point) eq. (9) and (15) of every neighbour j
become::

    f1_h a_j + f1_theta b_j + f1_t = beta f1_j                  # eq. (9)
    (h_2/h_1) f2_h a_j + f2_theta b_j + f2_t = beta f2_j        # eq. (15)

with f the image at the point (frame t at the matching band, whose grid the
matcher has made; any smooth image of the brightness serves as its regressor: the
gradients' own series, the mean of frames t and t + 1 at the flow band, gave the same
rendered figures within 1 % at a grid more per unit). They are solved in the same
weighted least squares as :func:`omniflow.solve.pooled.pooled_solution` (its local
model and its errors-in-variables correction), beta one more unknown.

The extra unknown costs accuracy where nothing changes brightness (it takes
up part of the texture's own signal: +9-16 % mean error on the static
rendered scenes), so a pool takes the gain answer only where the F statistic
of beta against the plain fit,

    F = (RSS_plain - RSS_gain) / (RSS_gain / (n_eff - P)),

exceeds ``OmniFlowConfig.brightness_gate`` (n_eff = 2 (sum w)^2 / sum w^2,
both units' rows, P the gain fit's unknowns, as the two-model test of
:mod:`omniflow.solve.decoupled`). Measured in docs/decisions/brightness_model.md.

With ``OmniFlowConfig.brightness.brightness_model`` "linear" the coupled gain may vary linearly
across the pool, (beta + beta_u u_j + beta_h dh_j) f_j: texture turning through shading
that stays put (a body spinning under fixed lights) changes brightness with no level
across a pool, only a gradient, which one gain cannot take up. The pool keeps one gain
where that passes the gate and the two slopes add nothing to it (their own F against one
gain), and takes the linear gain where its three columns' F against the plain fit passes
(docs/decisions/brightness_model.md).

:func:`gain_solution` is the coupled solve (eq. 14 assumed), used by
:func:`omniflow.solve.at_matches.make_solver` in the first solve and in the refinement;
:func:`decoupled_gain` the three-unknown model of :mod:`omniflow.solve.decoupled`
with the gain, used where that model was chosen.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from omniflow.solve.gain_kernels import gain_sums, nested_fits, small_solves
from omniflow.solve.gridpool import GridPools

__all__ = [
    "MIN_CHANGE",
    "MIN_GAIN_CHANGE",
    "MIN_GAIN_F",
    "MIN_RESIDUAL_DOF",
    "MIN_RESIDUAL_RATIO",
    "decoupled_gain",
    "decoupled_linear_gain",
    "gain_solution",
    "gated",
]

#: The least brightness change per frame, |beta|, that a pool's gain answer may correct:
#: a smaller fitted gain is the linearisation's model error, not a change (its F is not
#: tested); taking it doubled the median error on noise-free closed-form frames
#: (docs/decisions/brightness_model.md).
MIN_CHANGE = 0.002

#: The grid windows' gain sums (``pool_grid``, :meth:`GridPools.gain_sums`) filtered in
#: float32 (True, as the plain grid sums) or float64: float32 is faster and changes no
#: gate decision (docs/decisions/speed.md).
GRID_SINGLE = True

#: The fewest effective residual degrees of freedom (n_eff minus the unknowns) from which a
#: pool's residual variance is estimated for an F test (NaN below): with 2 the variance rests
#: on almost nothing and F passes any gate by chance (F(1, 2)'s 1 % point is 98.5). It kept
#: the static points at a spinner's silhouette and small static pools from switching
#: (docs/decisions/decoupling.md, docs/decisions/brightness_model.md).
MIN_RESIDUAL_DOF = 4.0

#: The least RSS_coupled / RSS_decoupled for which :func:`decoupled_linear_gain` reports
#: F_U (NaN below): eq. (14) is rejected only where dropping it at least halves the pool's
#: residual. F_U grows with the pool for the same relative misfit, so without this a small
#: systematic misfit in a large pool passes any fixed gate (docs/decisions/decoupling.md).
MIN_RESIDUAL_RATIO = 2.0

#: :func:`decoupled_linear_gain` answers with its gain only where the gain matters: the F of
#: the gain's three columns within the decoupled fit above this (F(3, 6)'s 1 % point is 9.8)
#: or a fitted term of at least :data:`MIN_GAIN_CHANGE`; elsewhere with the decoupled fit
#: without them over the same pool, which three extra unknowns only make noisier
#: (docs/decisions/decoupling.md).
MIN_GAIN_F = 10.0

#: The least fitted gain term, |beta| per frame or |beta_u|, |beta_h| over one pool radius,
#: that keeps :func:`decoupled_linear_gain`'s gain whatever its F, and the least term for
#: which :func:`gain_solution`'s coupled linear gain is tested at all: below it the terms
#: are model error (docs/decisions/decoupling.md, docs/decisions/brightness_model.md).
MIN_GAIN_CHANGE = 0.02


def gain_solution(
    derivs: tuple[NDArray, ...],
    f: tuple[NDArray, NDArray],
    h1: NDArray,
    h2: NDArray,
    theta: NDArray,
    idx: NDArray,
    w: NDArray,
    *,
    model: str,
    scale: float,
    min_conditioning: float,
    noise: tuple[float, float] = (0.0, 0.0),
    residual_noise: bool = False,
    gate: float | None = None,
    grid: GridPools | None = None,
    linear_gain: bool = False,
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Eq. (9) and (15) with a gain per pool, pooled as
    :func:`omniflow.solve.pooled.pooled_solution`.

    Parameters
    ----------
    derivs : six ndarrays, shape (N,)
        f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t at the points.
    f : two ndarrays, shape (N,)
        Each unit's image at the points.
    h1, h2, theta : ndarray, shape (N,)
    idx, w : ndarray, shape (N, K), or None
        Pools as :func:`omniflow.solve.pooled.neighbourhoods` returns them (unused with ``grid``).
    model, scale, min_conditioning
        As :func:`omniflow.solve.pooled.pooled_solution` (``relative`` radial model).
    noise, residual_noise
        Each unit's gradient-noise variance, per unit variance of the image
        noise measured from the residuals with ``residual_noise``
        (``eiv="residual"``), subtracted from the normal matrix as the plain
        solve does; (0, 0): none.
    gate : float, optional
        Correct only the pools whose F exceeds this (the others' answers are not
        taken, :func:`gated`): they keep the uncorrected fit.
    grid : GridPools, optional
        Pool over the grid's windows instead (:meth:`omniflow.solve.gridpool.GridPools.gain_sums`,
        the pools of the plain solve with ``pool_grid``).
    linear_gain : bool
        A gain varying linearly across the pool, (beta + beta_u u_j + beta_h dh_j) f_j
        (u_j and dh_j the tangential and radial offsets of neighbour j over ``scale``, as
        :func:`decoupled_linear_gain`'s), eq. (14) kept: texture turning through shading
        that stays put (a body spinning about its own axis under fixed lights) changes
        brightness with no level across the pool, only a gradient. Where one gain's F
        (the same Gram's leading block) passes ``gate`` the answer and F stay one gain's
        (a level of change, approach's face); elsewhere F is the statistic of the three
        gain columns against the plain fit, NaN where fewer than
        :data:`MIN_RESIDUAL_DOF` residual degrees of freedom estimate the variance or
        every term is below :data:`MIN_GAIN_CHANGE`. k-d tree pools only (not ``grid``).

    Returns
    -------
    dh1_dt, dtheta_dt : ndarray, shape (N,)
        The gain fit's flow; NaN where the pool has no solution.
    confidence : ndarray
        lambda_min / lambda_max of the information left on (a, h_1 b) once the
        other unknowns are free (the Schur complement).
    F : ndarray
        The statistic of beta against the plain fit over the same pool; NaN
        where either fit is singular or |beta| is below :data:`MIN_CHANGE`.
    """
    n = h1.size
    if linear_gain and grid is not None:
        raise ValueError("gain_solution: a linear gain needs the k-d tree pools, not grid")
    if grid is None:
        sums = model + "_lingain" if linear_gain else model
        M, v, yy, powers, x0, y0 = gain_sums(idx, w, np.arange(n), derivs, f, h1, h2, theta,
                                             model=sums, scale=scale)  # fmt: skip
        w2 = (w * w).sum(axis=1)
    else:
        M, v, yy, powers, w2 = grid.gain_sums(derivs, f, h1, h2, theta, linear=model == "linear",
                                              scale=scale, single=GRID_SINGLE)  # fmt: skip
        x0, y0 = _own_rows(derivs, f, h1, h2, M.shape[1])
    p = M.shape[1]
    one = np.zeros(n, bool)  # the pools answered with one gain (``linear_gain``)
    if linear_gain:
        x, conf, rss, _ = nested_fits(M, v, yy, min_conditioning, drop=p - 1)
        F = _linear_gain_f(M, v, yy, x, rss, powers[:, 0], w2, min_conditioning)
        # one gain where it passes the gate (the Gram's leading block: the flow and beta)
        # and the slopes do not add to it (their F against one gain)
        xc, confc, Fc = _one_gain(M[:, : p - 2, : p - 2], v[:, : p - 2], yy, powers[:, 0], w2,
                                  min_conditioning)  # fmt: skip
        if gate is not None:
            rss_c = yy - np.einsum("np,np->n", xc, v[:, : p - 2])
            Fs = _f(rss_c, rss, powers[:, 0], w2, p)[0] / 2.0
            one = gated(Fc, gate) & ~(gated(Fs, gate) & gated(F, gate))
            x = np.where(one[:, None], np.pad(xc, ((0, 0), (0, 2))), x)
            conf, F = np.where(one, confc, conf), np.where(one, Fc, F)
    else:
        x, conf, F = _one_gain(M, v, yy, powers[:, 0], w2, min_conditioning)
    a, c = x[:, 0], x[:, 1]
    if noise[0] > 0 or noise[1] > 0:  # errors in the variables, as the plain solve
        n1, n2 = noise
        if residual_noise:  # per unit variance of the image noise, measured from the residuals
            res = np.einsum("nup,np->nu", x0, x) - y0  # each point's own rows at its gain fit
            ok = np.isfinite(res).all(axis=1)
            if ok.sum() < 10:
                n1 = n2 = 0.0
            else:  # median of a squared normal: 0.455 var; f_t the difference of two fits
                var = np.median(res[ok] ** 2, axis=0) / 0.455 / 2.0
                n1, n2 = n1 * float(var[0]), n2 * float(var[1])
        sel = np.ones(n, bool) if gate is None else gated(F, gate)
        a, c, conf = a.copy(), c.copy(), conf.copy()
        for part, q in ((sel & ~one, p), (sel & one, p - 2)):  # the fit's own Gram block
            if not ((n1 > 0 or n2 > 0) and part.any()):
                continue
            u_powers = powers[part] if model == "linear" else powers[part, :1]
            ac, cc, confc = _corrected(M[part, :q, :q], v[part, :q], u_powers, (h2 / h1)[part],
                                       n1, n2, min_conditioning)  # fmt: skip
            use = np.isfinite(ac) & np.isfinite(cc)
            rows_c = np.flatnonzero(part)[use]
            a[rows_c], c[rows_c], conf[rows_c] = ac[use], cc[use], confc[use]
    return a, c / h1, conf, F


def _one_gain(M, v, yy, w1, w2, min_conditioning):
    """The fit of Gram ``M`` (N x P x P, its last unknown the gain beta), its confidence and
    the F statistic of beta against the fit without it; NaN where |beta| is below
    :data:`MIN_CHANGE` (too small a change to correct)."""
    x, conf, rss, rss0 = nested_fits(M, v, yy, min_conditioning, drop=M.shape[1] - 1)
    F = _f(rss0, rss, w1, w2, M.shape[1])[0]  # beta against the plain fit
    F[~(np.abs(x[:, -1]) >= MIN_CHANGE)] = np.nan
    return x, conf, F


def decoupled_gain(
    derivs: tuple[NDArray, ...],
    f: tuple[NDArray, NDArray],
    h1: NDArray,
    h2: NDArray,
    idx: NDArray,
    w: NDArray,
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The decoupled model of :mod:`omniflow.solve.decoupled` (U, h_1,i W, c) with a gain per pool.

    Unit u's row of neighbour j: (f_h, -f_h h_u,j / h_1,i, f_theta / h_1,i, -f) .
    (U, h_1,i W, c, beta) = -f_t (eq. 9 and 10 with the gain), constant model, no
    bias compensation, as :func:`omniflow.solve.decoupled.fits_from_sums`. Returns
    (dh1_dt, dh2_dt, dtheta_dt, F), F the statistic of beta against the
    three-unknown fit; NaN where a pool has no solution or |beta| is below
    :data:`MIN_CHANGE`. The rows of ``idx`` whose
    weights are all 0 are skipped (NaN).
    """
    n = h1.size
    out = [np.full(n, np.nan) for _ in range(4)]
    sel = np.flatnonzero(w.sum(axis=1) > 0)
    M, v, yy, _, _, _ = gain_sums(idx[sel], w[sel], sel, derivs, f, h1, h2, None,
                                  model="decoupled", scale=1.0)  # fmt: skip
    x, _, rss, rss0 = nested_fits(M, v, yy, 0.0, drop=M.shape[1] - 1)
    F = _f(rss0, rss, w[sel].sum(axis=1), (w[sel] ** 2).sum(axis=1), M.shape[1])[0]
    F[~(np.abs(x[:, -1]) >= MIN_CHANGE)] = np.nan  # too small a change to correct
    k = h2[sel] / h1[sel]
    out[0][sel], out[1][sel] = x[:, 0] - x[:, 1], x[:, 0] - k * x[:, 1]
    out[2][sel], out[3][sel] = x[:, 2] / h1[sel], F
    return tuple(out)


def decoupled_linear_gain(
    derivs: tuple[NDArray, ...],
    f: tuple[NDArray, NDArray],
    h1: NDArray,
    h2: NDArray,
    theta: NDArray,
    idx: NDArray,
    w: NDArray,
    *,
    scale: float,
    min_conditioning: float,
    slopes: bool = True,
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Eq. (14) tested with a gain varying linearly across the pool in both fits.

    Where a body turns under fixed lights (independent_movers' ring) its texture
    moves along the axis, so eq. (14) fails, and its brightness changes unevenly
    across a pool, which inflates both models' residuals: the plain two-model
    test (:mod:`omniflow.solve.decoupled`) and the one gain per pool do not find it.
    Here unit u's row of neighbour j carries the decoupled model of
    :func:`decoupled_gain` and a gain (beta + beta_u u_j + beta_h dh_j) f_u,j,
    u_j and dh_j the tangential and radial offsets of j from the point over
    ``scale`` (the linear pool model's u)::

        (f_h, -f_h h_u,j / h_1,i, f_theta / h_1,i, -f, -f u_j, -f dh_j)
            . (U, h_1,i W, c, beta, beta_u, beta_h) = -f_t

    one 6 x 6 weighted Gram per pool (:func:`omniflow.solve.gain_kernels.gain_sums`,
    ``decoupled_linear``). The coupled model with the same gain is the same Gram
    without the U column (U = 0 is eq. 14; the W column is the coupled radial one
    up to sign), so both fits come from one pass, and the statistic of U,

        F_U = (RSS_coupled - RSS_decoupled) / (RSS_decoupled / (n_eff - 6)),

    (n_eff = 2 (sum w)^2 / sum w^2, both units' rows) is eq. (14)'s test given
    the brightness model. Constant flow model, no bias compensation (as the
    decoupled model of :func:`omniflow.solve.decoupled.fits_from_sums`); each solve NaN
    where the information left on its first two unknowns (the Schur complement)
    is below ``min_conditioning`` (:func:`omniflow.solve.gain_kernels.small_solves`).
    ``slopes`` False: one gain per pool (beta only, 4 and 3 unknowns), the same test.

    The answer is the decoupled fit with the gain only where the gain matters (its three
    columns' F above :data:`MIN_GAIN_F` or a term of at least :data:`MIN_GAIN_CHANGE`),
    else the decoupled fit without them over the same pool (with ``slopes``).

    Returns
    -------
    dh1_dt, dh2_dt, dtheta_dt : ndarray, shape (N,)
        The decoupled fit's flow, dh_u = U - h_u W, dtheta = c / h_1,i, with the gain
        where it matters.
    F : ndarray, shape (N,)
        F_U; NaN where either fit has no solution, RSS_decoupled is 0, n_eff - 6 (the
        unknowns; ``slopes`` False: 4) is below :data:`MIN_RESIDUAL_DOF`,
        or RSS_coupled / RSS_decoupled below :data:`MIN_RESIDUAL_RATIO`: too little
        evidence, or too small a misfit, to drop eq. (14).
        The rows of ``idx`` whose weights are all 0 are skipped (NaN).
    """
    n = h1.size
    out = [np.full(n, np.nan) for _ in range(4)]
    sel = np.flatnonzero(w.sum(axis=1) > 0)
    model = "decoupled_linear" if slopes else "decoupled"
    M, v, yy, _, _, _ = gain_sums(idx[sel], w[sel], sel, derivs, f, h1, h2, theta,
                                  model=model, scale=scale)  # fmt: skip
    p = M.shape[1]
    x, _, rss, rss_c = nested_fits(M, v, yy, min_conditioning, drop=0)  # U = 0: eq. (14)
    ws = w[sel]
    F, n_eff = _f(rss_c, rss, ws.sum(axis=1), (ws * ws).sum(axis=1), p)
    k = h2[sel] / h1[sel]
    ok = (n_eff - p >= MIN_RESIDUAL_DOF) & (rss > 0) & (rss_c >= MIN_RESIDUAL_RATIO * rss)
    out[3][sel] = np.where(ok, F, np.nan)
    if slopes:  # the gain's answer only where its three columns matter
        x = _plain_where_no_gain(M, v, yy, x, rss, n_eff, min_conditioning)
    out[0][sel], out[1][sel] = x[:, 0] - x[:, 1], x[:, 0] - k * x[:, 1]
    out[2][sel] = x[:, 2] / h1[sel]
    return tuple(out)


def _plain_where_no_gain(M, v, yy, x, rss, n_eff, min_conditioning):
    """``x`` (N, 6), the decoupled fit with the linear gain, with its first three unknowns
    (U, h_1,i W, c) replaced by the fit without the gain's three columns (the Gram's
    leading 3 x 3 block, the same pool) where the gain does not matter: the F statistic
    of those columns, ((RSS_plain - RSS) / 3) / (RSS / (n_eff - 6)), not above
    :data:`MIN_GAIN_F` and every fitted term, |beta|, |beta_u|, |beta_h|, below
    :data:`MIN_GAIN_CHANGE`."""
    x3, F = _without_gain(M, v, yy, rss, n_eff, min_conditioning)
    small = ~(F > MIN_GAIN_F) & (np.abs(x[:, 3:6]) < MIN_GAIN_CHANGE).all(axis=1)
    plain = small & np.isfinite(x3).all(axis=1)
    out = x.copy()
    out[plain, :3] = x3[plain]
    return out


def _without_gain(M, v, yy, rss, n_eff, min_conditioning):
    """The decoupled fit without the gain's three columns, (N, 3), and their F statistic
    against the fit with them (RSS ``rss``): Gram ``M`` (N, 6, 6), ``v`` (N, 6), ``yy``."""
    x3, _ = small_solves(M[:, :3, :3], v[:, :3], min_conditioning)
    rss3 = yy - np.einsum("np,np->n", x3, v[:, :3])
    with np.errstate(divide="ignore", invalid="ignore"):
        return x3, (rss3 - rss) / 3.0 / (rss / (n_eff - M.shape[1]))


def _linear_gain_f(M, v, yy, x, rss, w1, w2, min_conditioning):
    """The F statistic of a linear gain's three columns (the last of Gram ``M``, N x P x P)
    against the plain fit over the same pool (the leading P - 3 block), for
    :func:`gain_solution`: ((RSS_plain - RSS) / 3) / (RSS / (n_eff - P)); NaN where
    n_eff - P is below :data:`MIN_RESIDUAL_DOF` or every fitted term, |beta|, |beta_u|,
    |beta_h|, below :data:`MIN_GAIN_CHANGE` (model error, not a change)."""
    p = M.shape[1]
    xp, _ = small_solves(M[:, : p - 3, : p - 3], v[:, : p - 3], min_conditioning)
    rss_plain = yy - np.einsum("np,np->n", xp, v[:, : p - 3])
    F, n_eff = _f(rss_plain, rss, w1, w2, p)
    F = F / 3.0
    small = ~(np.abs(x[:, p - 3 :]) >= MIN_GAIN_CHANGE).any(axis=1)
    F[small | ~(n_eff - p >= MIN_RESIDUAL_DOF)] = np.nan
    return F


def gated(F: NDArray, gate: float | NDArray, *answers: NDArray) -> NDArray:
    """Where the gain answer is taken: F above ``gate`` (one, or one per point) and every
    answer finite."""
    with np.errstate(invalid="ignore"):
        use = F > gate
    for v in answers:
        use &= np.isfinite(v)
    return use


def _f(rss_without, rss_with, w1, w2, p):
    """(RSS_without - RSS_with) / (RSS_with / (n_eff - p)), the statistic of the unknowns
    a fit of ``p`` adds; n_eff = 2 w1^2 / w2 (both units' rows; ``w1``, ``w2`` the pool's
    sums of weights and of squared weights)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        n_eff = 2.0 * w1**2 / w2
        return (rss_without - rss_with) / (rss_with / (n_eff - p)), n_eff


def _own_rows(derivs, f, h1, h2, p):
    """Both units' rows (N, 2, P) and right sides (N, 2) of each point's own equations
    (u = 0, relative factor 1), the unknowns of :func:`omniflow.solve.gain_kernels.gain_sums`."""
    x0 = np.zeros((h1.size, 2, p))
    x0[:, 0, 0], x0[:, 1, 0] = derivs[0], (h2 / h1) * derivs[3]  # eq. (9), eq. (15)
    x0[:, 0, 1], x0[:, 1, 1] = derivs[1] / h1, derivs[4] / h1
    x0[:, 0, -1], x0[:, 1, -1] = -f[0], -f[1]
    return x0, np.stack([-derivs[2], -derivs[5]], axis=1)


def _corrected(M, v, powers, k, n1, n2, min_conditioning):
    """(a, c, confidence) with the expected gradient-noise power subtracted from the
    normal matrix's gradient entries (bias-compensated least squares, as
    :func:`omniflow.solve.pooled.pooled_solution`: a row's noise n1 + n2 k^2 times its weight and
    power of u, the neighbours' ratios taken as the point's own); NaN where the signal
    does not outweigh the noise on both components or the result is not positive definite."""
    per_row = [n1 * s + n2 * k**2 * s for s in powers.T]
    blocks = [(0,), (1,)] if powers.shape[1] == 1 else [(0, 2), (1, 3)]  # a, c and their slopes
    Mc = M.copy()
    for block in blocks:
        for ii, ci in enumerate(block):
            for jj, cj in enumerate(block):
                Mc[:, ci, cj] -= per_row[ii + jj]
    x, conf = small_solves(Mc, v, min_conditioning, positive=True)
    strong = (M[:, 0, 0] > 2.0 * per_row[0]) & (M[:, 1, 1] > 2.0 * per_row[0])
    x[~strong] = np.nan
    return x[:, 0], x[:, 1], conf
