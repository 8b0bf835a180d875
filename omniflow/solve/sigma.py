"""A predicted standard deviation for every flow and range estimate.

Three columns beside the result's (:data:`SIGMA_COLUMNS`), made from the columns
themselves and the measured image noise when the result's sigma is first read
(:func:`omniflow.pipeline.predicted_sigmas`), so no existing column changes:

* ``sigma_flow1``, ``sigma_flow2``: the predicted root-mean-square endpoint error of
  each unit's pixel flow (dx, dy), px/frame. The noise part is the covariance of the
  least squares of eq. (9) and (15): for unknowns u = (dh1_dt, h1 dtheta_dt) and rows
  A_j over the point's pool (one row per unit and neighbour, weights w_j; one point
  for the direct solution, eq. 16), Cov u = N^-1 (sum_j w_j^2 var_j A_j^T A_j) N^-1,
  N = sum_j w_j A_j^T A_j, with var_j the variance of the equation's residual:
  the fitted frame difference (2 rho sigma^2, rho the share of white noise the flow
  series keeps) plus the gradient noise times the flow (g (a^2 + (h1 b)^2)).
  cam1's prediction is sqrt(trace Cov u); cam2's is h2/h1 times it (eq. 14) where
  eq. (14) is kept (``coupled``), else inf (below).
  What noise does not explain (the series' truncation, the linearisation, a wrong
  match) enters as a share of the flow and a floor, and a scale calibrates the whole:
  sigma^2 = scale^2 (sigma_ls^2 + (share |v|)^2 + floor^2).
* ``sigma_r``: range, m. The match's disparity error from the noise (the edge's
  localisation, sigma_n^2 / f_h^2 summed over both units and divided by the patch
  length), from its score ((1 - score) times a squared-pixel constant) and a floor,
  through |dr/dh2| = (d + r)^2 / (s v2) (eq. 5).

Where the eq. (14) test failed (``coupled`` = 0) ``sigma_flow2`` and ``sigma_r`` are inf,
no confident answer (:func:`omniflow.result.confident`): for a static point whose two
images are the same scene point eq. (14) holds exactly (eq. 3 and 4 differentiated with
dh = 0), so a failed test means either motion along the axis or a match pairing two
scene points, which the test cannot tell apart. Both columns rest on the match: r is
eq. (5) of its disparity, cam2's flow is read at the matched (x2, y2), and the covariance
above is that of the coupled model the test rejected. cam1's flow is eq. (9) on cam1's
own pixels (the decoupled solve gives it its own radial flow), so ``sigma_flow1`` stays.

The constants are :class:`SigmaModel`'s, chosen on the benchmark suite's train split
(docs/decisions/confidence.md, which also gives the test split's coverage).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from omniflow.fit.noise import NoiseLevel, temporal_noise
from omniflow.result import SIGMA_COLUMNS

__all__ = [
    "MODELS",
    "SIGMA_COLUMNS",
    "SigmaModel",
    "flow_covariance",
    "model_for",
    "point_noise",
    "sigmas",
]


@dataclass(frozen=True)
class SigmaModel:
    """The constants of the prediction (module docstring), chosen on the train split.

    Attributes
    ----------
    flow_scale, flow_share, flow_floor : float
        sigma_flow^2 = flow_scale^2 (sigma_ls^2 + (flow_share |v|)^2 + flow_floor^2);
        ``flow_floor`` in px/frame.
    range_scale, range_score, range_floor : float
        sigma_disp^2 = range_scale^2 (sigma_loc^2 + range_score (1 - score) + range_floor^2),
        ``range_score`` in px^2, ``range_floor`` in px.
    patch : int
        Samples along the radial line a match's localisation averages over.
    """

    flow_scale: float = 1.0
    flow_share: float = 0.0
    flow_floor: float = 0.0
    range_scale: float = 1.0
    range_score: float = 0.0
    range_floor: float = 0.0
    patch: int = 7


#: The constants per solver: the direct solution (eq. 16), the pooled solver on k-d tree
#: pools and on grid pools (``pool_grid``); chosen on the train split
#: (docs/decisions/confidence.md).
#: The direct solution (the paper preset) is not calibrated: its constants are neutral,
#: so its sigmas are the noise's alone.
MODELS: dict[str, SigmaModel] = {
    "direct": SigmaModel(),
    "pooled": SigmaModel(flow_scale=0.641, flow_share=0.7, flow_floor=0.01,
                         range_scale=0.817, range_score=100.0, range_floor=0.05),
    "grid": SigmaModel(flow_scale=0.783, flow_share=0.3, flow_floor=0.0,
                       range_scale=1.54, range_score=0.0, range_floor=0.1),
}  # fmt: skip


def model_for(config) -> SigmaModel:
    """The :data:`MODELS` entry of a configuration's solver."""
    if config.solver != "pooled":
        return MODELS["direct"]
    return MODELS["grid" if config.grid_pools else "pooled"]


#: Rows of each stripe the noise is measured on, and the stripes' period (rows): a
#: twelfth of the tile rows (the middle one of three in each kept stripe), and the
#: whole-pixel motion searched per tile (:func:`point_noise`): the estimate in a tenth
#: of the whole annulus's time.
STRIPE, STRIPE_PERIOD, SEARCH = 48, 192, 1


def point_noise(frame_t: NDArray, frame_t1: NDArray, mask: NDArray, x: NDArray, y: NDArray):
    """Each point's image noise sigma (grey): the temporal estimate sigma^2 = a I + b
    (:func:`omniflow.fit.noise.temporal_noise`) of frames t and t + 1 at the brightness
    of frame t's pixel holding the point, and the fitted level.

    From 2 :data:`STRIPE_PERIOD` rows up (smaller images whole), measured on stripes of
    :data:`STRIPE` rows every :data:`STRIPE_PERIOD` rows, stacked
    into one image (each stripe's first and last rows left out of the mask, so no tile
    straddles two stripes): its tiles are a twelfth of the whole annulus's, spread over
    it, each searched for a whole-pixel motion of up to :data:`SEARCH` px (the flow
    steps' motions are mostly sub-pixel; the fit follows what is left).
    """
    f0, f1 = (np.asarray(f, dtype=np.float64) for f in (frame_t, frame_t1))
    rows = np.arange(f0.shape[0])
    # stripes from two periods up (512 px: three stripes); a smaller image whole
    keep = rows % STRIPE_PERIOD < STRIPE if rows.size >= 2 * STRIPE_PERIOD else rows >= 0
    inner = np.asarray(mask, bool)[keep].copy()
    if not keep.all():
        edge = rows[keep] % STRIPE_PERIOD
        inner[(edge == 0) | (edge == STRIPE - 1)] = False  # no tile across a seam
    level = temporal_noise(f0[keep], f1[keep], inner, search=SEARCH)
    h, w = f0.shape
    ok = np.isfinite(x) & np.isfinite(y)
    j = np.clip(np.floor(np.where(ok, x, 0.0)).astype(np.intp), 0, w - 1)
    i = np.clip(np.floor(np.where(ok, y, 0.0)).astype(np.intp), 0, h - 1)
    return _sigma_at(level, f0[i, j]), level


def _sigma_at(level: NoiseLevel, intensity: NDArray) -> NDArray:
    """sqrt(a I + b), 0 where the level could not be measured (no tile in the mask)."""
    if not (math.isfinite(level.a) and math.isfinite(level.b)):
        return np.zeros(np.shape(intensity))
    return np.asarray(level.sigma_at(intensity), dtype=np.float64)


def flow_covariance(
    cols: dict[str, NDArray],
    var_eq: tuple[NDArray, NDArray],
    idx: NDArray | None = None,
    w: NDArray | None = None,
) -> tuple[NDArray, NDArray, NDArray]:
    """Cov of u = (dh1_dt, h1 dtheta_dt) from eq. (9) and (15), per point, px^2/frame^2.

    ``cols``: the result columns (f1_h ... f2_theta, h1, h2); ``var_eq``: each unit's
    residual variance per point (grey^2/frame^2). ``idx``, ``w``: the pools of
    :func:`omniflow.solve.pooled.neighbourhoods` (index N = none, weight 0), pooled
    with the relative radial model (a_j = a h1_j / h1_i); None: each point alone
    (eq. 16). Returns (C_aa, C_ab, C_bb); NaN where the system is singular.
    """
    h1 = np.asarray(cols["h1"], np.float64)
    k = np.asarray(cols["h2"], np.float64) / h1
    n = h1.size
    if idx is None:
        idx, w = np.arange(n)[:, None], np.ones((n, 1))
    pad = lambda v: np.append(np.asarray(v, np.float64), 0.0)  # noqa: E731 (index N: 0)
    hj = pad(h1)[idx] / np.where(h1 > 0, h1, np.nan)[:, None]  # a_j = a h1_j / h1_i
    rows = (  # (coefficient of a_i, coefficient of h1_i b_i, residual variance) per unit
        (pad(cols["f1_h"])[idx] * hj, pad(cols["f1_theta"])[idx], pad(var_eq[0])[idx]),
        (pad(k * cols["f2_h"])[idx] * hj, pad(cols["f2_theta"])[idx], pad(var_eq[1])[idx]),
    )
    n_aa = n_ab = n_bb = m_aa = m_ab = m_bb = 0.0
    for p, q, v in rows:
        q = q / h1[:, None]  # f_theta b = (f_theta / h1_i) (h1_i b)
        n_aa = n_aa + (w * p * p).sum(1)
        n_ab = n_ab + (w * p * q).sum(1)
        n_bb = n_bb + (w * q * q).sum(1)
        ww = w * w * v
        m_aa = m_aa + (ww * p * p).sum(1)
        m_ab = m_ab + (ww * p * q).sum(1)
        m_bb = m_bb + (ww * q * q).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        det = n_aa * n_bb - n_ab * n_ab
        det = np.where(det > 1e-12 * (n_aa * n_bb), det, np.nan)
        # N^-1 = [[n_bb, -n_ab], [-n_ab, n_aa]] / det; C = N^-1 M N^-1
        i_aa, i_ab, i_bb = n_bb / det, -n_ab / det, n_aa / det
        t_aa, t_ab = i_aa * m_aa + i_ab * m_ab, i_aa * m_ab + i_ab * m_bb
        t_ba, t_bb = i_ab * m_aa + i_bb * m_ab, i_ab * m_ab + i_bb * m_bb
        c_aa = t_aa * i_aa + t_ab * i_ab
        c_ab = t_aa * i_ab + t_ab * i_bb
        c_bb = t_ba * i_ab + t_bb * i_bb
    return c_aa, c_ab, c_bb


def sigmas(
    cols: dict[str, NDArray],
    *,
    noise: tuple[NDArray, NDArray],
    value_share: tuple[float, float],
    gradient_var: tuple[float, float],
    d: float,
    s: float,
    v2: float,
    pools: tuple[NDArray, NDArray] | None = None,
    model: SigmaModel | None = None,
) -> dict[str, NDArray]:
    """The columns of :data:`SIGMA_COLUMNS` for the result columns ``cols``.

    Parameters
    ----------
    cols : dict of ndarray, shape (N,)
        The result's columns (:data:`omniflow.result.COLUMNS`).
    noise : (ndarray, ndarray), each shape (N,)
        Each unit's image noise sigma at the point (cam1 at (x, y), cam2 at (x2, y2)),
        grey (:func:`point_noise`).
    value_share : (float, float)
        Each unit's share of white pixel noise variance that the flow series keeps
        in its values (rho; ``omniflow.fit.series.value_noise_share``).
    gradient_var : (float, float)
        Each unit's gradient-component noise variance per unit pixel variance,
        (grey/px)^2 per grey^2 (``omniflow.fit.series.gradient_noise`` at sigma 1).
    d, s, v2 : float
        The rig's d (m), baseline s (m) and cam2's image distance v (px), for eq. (5).
    pools : (idx, w), optional
        The flow step's pools (pooled solver); None: the direct solution.
    model : SigmaModel, optional
        The constants; ``SigmaModel()`` by default.
    """
    model = SigmaModel() if model is None else model
    h1 = np.asarray(cols["h1"], np.float64)
    h2 = np.asarray(cols["h2"], np.float64)
    a = np.asarray(cols["dh1_dt"], np.float64)
    hb = h1 * np.asarray(cols["dtheta_dt"], np.float64)
    move2 = a * a + hb * hb
    var_eq = tuple(
        2.0 * value_share[u] * noise[u] ** 2 + gradient_var[u] * noise[u] ** 2 * move2
        for u in (0, 1)
    )
    c_aa, _, c_bb = flow_covariance(cols, var_eq, *(pools or (None, None)))
    ls2 = c_aa + c_bb
    speed1 = np.hypot(np.asarray(cols["dx"], np.float64), np.asarray(cols["dy"], np.float64))
    f1 = model.flow_scale * np.sqrt(ls2 + (model.flow_share * speed1) ** 2 + model.flow_floor**2)
    k = h2 / h1  # eq. (14): cam2's polar flow is h2/h1 times cam1's
    coupled = np.asarray(cols.get("coupled", np.ones(h1.size)), np.float64) > 0.5
    f2 = np.where(coupled, k * f1, np.inf)  # flagged: no confident answer (docstring)
    # the disparity's localisation: each unit's edge placed to sigma_n / |f_h| per sample
    with np.errstate(divide="ignore", invalid="ignore"):
        loc2 = (
            noise[0] ** 2 / np.asarray(cols["f1_h"], np.float64) ** 2
            + noise[1] ** 2 / np.asarray(cols["f2_h"], np.float64) ** 2
        ) / model.patch
    score = np.clip(np.asarray(cols["score"], np.float64), -1.0, 1.0)
    disp = model.range_scale * np.sqrt(
        loc2 + model.range_score * (1.0 - score) + model.range_floor**2
    )
    r = np.asarray(cols["r"], np.float64)
    sr = np.where(coupled, (d + r) ** 2 / (s * v2) * disp, np.inf)  # |dr/dh2|, eq. (5)
    return {"sigma_flow1": f1, "sigma_flow2": f2, "sigma_r": sr}
