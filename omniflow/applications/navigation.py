"""Uses of omni flow named in the paper's section 6.

All quantities are in the rig frame of :mod:`omniflow.conventions`: ``r`` in
metres from the axis, ``theta`` the azimuth in radians (counter-clockwise seen
from above, from +X), velocities per frame interval (multiply by
``1 / frame_interval`` for seconds). The robot and the objects move on the
floor (no motion along the axis), the assumption under eq. (14).

- :func:`time_to_contact`: ``-r / (dr/dt)``, braking, time of arrival, from the
  range rate of the result (:func:`omniflow.paper.flow.radial_velocity`,
  ``dr/dt = -(d + r) (dh_1/dt) / h_1``, eq. 11, 13; or
  :func:`omniflow.paper.flow.radial_velocity_stereo` from both units' radial flows
  without eq. (14), for points that move along the axis: the ``coupled`` = False
  points of the result).
- :func:`region_flow` and :func:`steering_heading`: the mean flow over an
  object's points, and the heading that homes in on it (steer with its flow)
  or avoids it (steer against it).
- :func:`position_fix`: the robot's pose ``(x, y, yaw)`` in the world from the
  ``(r, theta)`` of two or more landmarks at known world positions.
- :func:`odometry`: the robot's yaw rate and velocity from the flow of many
  points, independently moving points rejected as outliers.

Odometry model (OMNIFLOW_MATH.md). A static point seen from a robot that moves
with velocity ``(V_x, V_y)`` and yaw rate ``w`` (both in the rig frame) moves,
relative to the rig, with ``dp/dt = -V - w x p``; in cylindrical terms::

    dr/dt         = -(V_x cos theta + V_y sin theta)
    r dtheta/dt   = -w r + V_x sin theta - V_y cos theta

Both rows are linear in ``(w, V_x, V_y)`` and in metres per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.conventions import wrap_angle as _wrap

__all__ = [
    "OdometryFit",
    "PoseFix",
    "RegionFlow",
    "odometry",
    "position_fix",
    "region_flow",
    "steering_heading",
    "time_to_contact",
]


def _arrays(*values: ArrayLike) -> list[NDArray]:
    """Float arrays broadcast to one shape."""
    return list(np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in values)))


# -- radial velocity and time to contact ------------------------------------------


def time_to_contact(r: ArrayLike, dr_dt: ArrayLike) -> NDArray:
    """Frames until a point at range ``r`` reaches the axis at its present dr/dt.

    ``-r / (dr/dt)`` where the point approaches (dr/dt < 0); ``inf`` where it
    keeps its range or recedes. Multiply by the frame interval for seconds.
    """
    r, dr_dt = _arrays(r, dr_dt)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(dr_dt < 0, -r / dr_dt, np.inf)


# -- mean flow of a region and steering ----------------------------------------------


@dataclass(frozen=True)
class RegionFlow:
    """The mean flow of a region (an object's points).

    Attributes
    ----------
    count : int
        Points averaged.
    theta : float
        Bearing of the region's centroid in the floor plane, radians.
    r : float
        Range of that centroid, metres.
    dr_dt, dtheta_dt : float
        Radial velocity (m/frame) and bearing rate (rad/frame) of the
        centroid, from the mean relative velocity.
    velocity : (float, float)
        Mean velocity of the region's points relative to the rig, (v_X, v_Y)
        in m/frame, rig frame: ``dr/dt e_r + r dtheta/dt e_theta`` averaged.
    image_flow : (float, float)
        Mean camera-1 image flow (dx, dy) in pixels, when given (else nan).
    time_to_contact : float
        ``-r / (dr/dt)`` of the centroid in frames (inf if not approaching).
    """

    count: int
    theta: float
    r: float
    dr_dt: float
    dtheta_dt: float
    velocity: tuple[float, float]
    image_flow: tuple[float, float]
    time_to_contact: float

    @property
    def position(self) -> tuple[float, float]:
        """Centroid (X, Y) of the region in the rig frame, metres."""
        return (self.r * math.cos(self.theta), self.r * math.sin(self.theta))


def region_flow(
    theta: ArrayLike,
    r: ArrayLike,
    dr_dt: ArrayLike,
    dtheta_dt: ArrayLike,
    *,
    mask: ArrayLike | None = None,
    dx: ArrayLike | None = None,
    dy: ArrayLike | None = None,
) -> RegionFlow:
    """Average the omni flow over a region (paper section 6).

    Each point's flow is turned into its velocity relative to the rig in the
    floor plane, ``dr/dt e_r + r dtheta/dt e_theta`` (the same vector
    whatever the bearing, so averaging is meaningful), and averaged; so are the
    positions. The centroid's bearing rate and radial velocity follow from the
    mean velocity and mean position.

    Parameters
    ----------
    theta, r, dr_dt, dtheta_dt : ndarray, shape (N,)
        Per point: bearing (rad), range (m), dr/dt (m/frame), dtheta/dt
        (rad/frame), e.g. the columns of :class:`omniflow.pipeline.OmniFlowResult`.
    mask : ndarray of bool, shape (N,), optional
        The region's points (default: all). Points with non-finite values are
        dropped.
    dx, dy : ndarray, shape (N,), optional
        Camera-1 image flow in pixels, averaged into ``image_flow``.

    Raises
    ------
    ValueError
        If no finite point is left in the region.
    """
    theta, r, dr_dt, dtheta_dt = _arrays(theta, r, dr_dt, dtheta_dt)
    keep = np.isfinite(theta) & np.isfinite(r) & np.isfinite(dr_dt) & np.isfinite(dtheta_dt)
    if mask is not None:
        keep &= np.broadcast_to(np.asarray(mask, dtype=bool), keep.shape)
    if not keep.any():
        raise ValueError("region_flow: the region has no point with finite r, theta and flow")
    t, rr, vr, wt = theta[keep], r[keep], dr_dt[keep], dtheta_dt[keep]
    c, s = np.cos(t), np.sin(t)
    px, py = float(np.mean(rr * c)), float(np.mean(rr * s))
    vt = rr * wt  # tangential velocity, m/frame
    vx = float(np.mean(vr * c - vt * s))
    vy = float(np.mean(vr * s + vt * c))
    r_c = math.hypot(px, py)
    th_c = math.atan2(py, px)
    radial = (px * vx + py * vy) / r_c if r_c > 0 else float("nan")
    bearing_rate = (px * vy - py * vx) / r_c**2 if r_c > 0 else float("nan")
    if dx is not None and dy is not None:
        fx = np.broadcast_to(np.asarray(dx, dtype=float), keep.shape)[keep]
        fy = np.broadcast_to(np.asarray(dy, dtype=float), keep.shape)[keep]
        image_flow = (float(np.nanmean(fx)), float(np.nanmean(fy)))
    else:
        image_flow = (float("nan"), float("nan"))
    ttc = float(time_to_contact(r_c, radial))
    return RegionFlow(int(keep.sum()), th_c, r_c, radial, bearing_rate, (vx, vy), image_flow, ttc)


def steering_heading(region: RegionFlow, *, mode: str = "home_in", lead: float = 1.0) -> float:
    """Heading (rig-frame azimuth, radians) to steer to home in on or avoid a region.

    The paper steers "in the same direction" as an object's average flow to
    follow it and in the opposite direction to avoid it. Made concrete: the
    object's position ``lead`` frames ahead, extrapolated with its mean
    relative velocity, ``p = position + lead * velocity``, so the bearing turns
    the way the object's flow goes (by about ``lead * dtheta/dt``).

    - ``mode="home_in"``: head for ``p``: ``atan2(p_Y, p_X)``.
    - ``mode="avoid"``: head straight away from ``p``: that angle + pi.

    Both use relative motion only, so they hold for a moving robot and a
    moving object alike. With ``lead=0`` the heading is the present bearing
    (or its opposite). The result is wrapped to [-pi, pi).
    """
    if mode not in ("home_in", "avoid"):
        raise ValueError(f"steering_heading: mode={mode!r}: expected 'home_in' or 'avoid'")
    if not (math.isfinite(lead) and lead >= 0):
        raise ValueError(f"steering_heading: lead={lead!r}: expected a finite number >= 0")
    px, py = region.position
    px += lead * region.velocity[0]
    py += lead * region.velocity[1]
    heading = math.atan2(py, px) + (math.pi if mode == "avoid" else 0.0)
    return float(_wrap(heading))


# -- position fix from landmarks --------------------------------------------------------


@dataclass(frozen=True)
class PoseFix:
    """Robot pose in the world from landmarks.

    Attributes
    ----------
    x, y : float
        Position of the rig's axis on the floor, world metres.
    yaw : float
        Rotation of the rig's +X from the world's +X, radians, in [-pi, pi).
    residuals : ndarray, shape (N, 2)
        Per landmark: range residual (m) and bearing residual (rad), observed
        minus predicted from the fitted pose.
    rms_position : float
        RMS distance (m) between observed and predicted landmark positions.
    cost : float
        Final value of the least-squares cost (0.5 * sum of squared scaled residuals).
    """

    x: float
    y: float
    yaw: float
    residuals: NDArray
    rms_position: float
    cost: float


def position_fix(
    landmarks: ArrayLike,
    r: ArrayLike,
    theta: ArrayLike,
    *,
    sigma_r: float = 1.0,
    sigma_theta: float = 1.0,
    loss: str = "linear",
) -> PoseFix:
    """Fix the robot's pose ``(x, y, yaw)`` from landmarks at known world positions.

    A landmark at world ``L = (L_X, L_Y)`` is seen at rig-frame range ``r`` and
    bearing ``theta``: ``L = (x, y) + Rot(yaw) r (cos theta, sin theta)``.
    The pose is the nonlinear least-squares fit
    (:func:`scipy.optimize.least_squares`) of the range and bearing residuals
    ``(r - r_pred) / sigma_r`` and ``wrap(theta - theta_pred) * r / sigma_theta``
    (the bearing residual as an arc length, so the defaults weigh both in
    metres), started from the closed-form rigid 2-D alignment of the observed
    to the known points.

    Parameters
    ----------
    landmarks : ndarray, shape (N, 2)
        World (X, Y) of each landmark, metres.
    r, theta : ndarray, shape (N,)
        Observed range (m) and bearing (rad, rig frame) of each landmark.
    sigma_r, sigma_theta : float
        Relative weights: expected range error (m) and bearing error
        (rad * m, i.e. the tangential position error).
    loss : str
        Passed to ``least_squares`` (``"soft_l1"`` etc. resist a misidentified
        landmark when there are more than two).

    Raises
    ------
    ValueError
        Fewer than two usable landmarks (one fixes position only up to a
        rotation about it: under-determined), landmarks at one place, or a
        non-positive range.
    """
    from scipy.optimize import least_squares

    lm = np.asarray(landmarks, dtype=float)
    r = np.asarray(r, dtype=float).ravel()
    theta = np.asarray(theta, dtype=float).ravel()
    if lm.ndim != 2 or lm.shape[1] != 2:
        raise ValueError(f"position_fix: landmarks must have shape (N, 2), got {lm.shape}")
    if not (lm.shape[0] == r.size == theta.size):
        raise ValueError(
            f"position_fix: {lm.shape[0]} landmarks but {r.size} ranges and {theta.size} bearings"
        )
    ok = np.isfinite(lm).all(axis=1) & np.isfinite(r) & np.isfinite(theta)
    if np.any(r[ok] <= 0):
        raise ValueError("position_fix: every landmark range r must be > 0")
    lm, r, theta = lm[ok], r[ok], theta[ok]
    if lm.shape[0] < 2:
        raise ValueError(
            f"position_fix: under-determined: {lm.shape[0]} usable landmark(s); the pose "
            "(x, y, yaw) needs at least 2 landmarks at distinct known positions"
        )
    spread = np.max(np.linalg.norm(lm - lm.mean(axis=0), axis=1))
    if spread < 1e-9 * max(1.0, float(np.max(np.abs(lm)))):
        raise ValueError(
            "position_fix: under-determined: all landmarks are at the same world position; "
            "the yaw cannot be fixed"
        )
    if not (sigma_r > 0 and sigma_theta > 0):
        raise ValueError("position_fix: sigma_r and sigma_theta must be > 0")

    obs = np.column_stack([r * np.cos(theta), r * np.sin(theta)])  # rig frame
    x0 = _rigid_2d(obs, lm)

    def predicted(p):
        x, y, yaw = p
        rel = lm - (x, y)
        c, s = math.cos(yaw), math.sin(yaw)
        rx = c * rel[:, 0] + s * rel[:, 1]  # Rot(-yaw) (L - t)
        ry = -s * rel[:, 0] + c * rel[:, 1]
        return np.hypot(rx, ry), np.arctan2(ry, rx)

    def residual(p):
        rp, tp = predicted(p)
        return np.concatenate([(r - rp) / sigma_r, _wrap(theta - tp) * r / sigma_theta])

    sol = least_squares(residual, x0, loss=loss, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    rp, tp = predicted(sol.x)
    res = np.column_stack([r - rp, _wrap(theta - tp)])
    pred_xy = np.column_stack([rp * np.cos(tp), rp * np.sin(tp)])
    rms = float(np.sqrt(np.mean(np.sum((obs - pred_xy) ** 2, axis=1))))
    x, y, yaw = sol.x
    return PoseFix(float(x), float(y), float(_wrap(yaw)), res, rms, float(sol.cost))


def _rigid_2d(src: NDArray, dst: NDArray) -> NDArray:
    """(x, y, yaw) of the rotation + translation taking ``src`` onto ``dst`` (least squares)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - cs, dst - cd
    yaw = math.atan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b))
    c, s = math.cos(yaw), math.sin(yaw)
    t = cd - np.array([c * cs[0] - s * cs[1], s * cs[0] + c * cs[1]])
    return np.array([t[0], t[1], yaw])


# -- odometry -------------------------------------------------------------------------


@dataclass(frozen=True)
class OdometryFit:
    """The robot's motion fitted to the flow of many points.

    Attributes
    ----------
    w : float
        Yaw rate, rad/frame (counter-clockwise seen from above positive).
    V_x, V_y : float
        Velocity of the robot in the rig frame, m/frame.
    inliers : ndarray of bool, shape (N,)
        Points consistent with a static scene; False: independently moving
        (or mismatched) points, and points without finite data.
    residuals : ndarray, shape (N,)
        Per point, RMS over its equations of (observed - model), m/frame.
    scale : float
        Robust residual scale (m/frame) the inlier threshold was based on.
    threshold : float
        Inlier threshold used, m/frame.
    """

    w: float
    V_x: float
    V_y: float
    inliers: NDArray
    residuals: NDArray
    scale: float
    threshold: float

    @property
    def inlier_fraction(self) -> float:
        return float(np.mean(self.inliers)) if self.inliers.size else 0.0

    def own_velocity(
        self, theta: ArrayLike, r: ArrayLike, dr_dt: ArrayLike, dtheta_dt: ArrayLike
    ) -> NDArray:
        """Each point's velocity not explained by the robot's motion, (N, 2) rig (X, Y), m/frame.

        Observed minus the fitted static-scene model (the module's odometry
        model), turned from (radial, tangential) into the rig frame: for an
        object translating on the floor, every one of its points gets the
        object's own velocity, so its points agree with one another.
        """
        theta, r, dr_dt, dtheta_dt = _arrays(theta, r, dr_dt, dtheta_dt)
        A, b = _odometry_rows(theta.ravel(), r.ravel(), dr_dt.ravel(), dtheta_dt.ravel(), 1.0)
        res = b - A @ np.array([self.w, self.V_x, self.V_y])  # (N, 2): tangential, radial
        c, s = np.cos(theta.ravel()), np.sin(theta.ravel())
        d_t, d_r = res[:, 0], res[:, 1]
        return np.column_stack([d_r * c - d_t * s, d_r * s + d_t * c])


def _odometry_rows(theta, r, dr_dt, dtheta_dt, radial_weight):
    """Design matrix (N, k, 3) and observations (N, k) in m/frame; k = 1 or 2 rows per point."""
    c, s = np.cos(theta), np.sin(theta)
    tang_a = np.stack([-r, s, -c], axis=-1)  # r dtheta/dt = -w r + V_x s - V_y c
    tang_b = r * dtheta_dt
    if radial_weight == 0:
        return tang_a[:, None, :], tang_b[:, None]
    rad_a = radial_weight * np.stack([np.zeros_like(r), -c, -s], axis=-1)  # dr/dt
    rad_b = radial_weight * dr_dt
    return np.stack([tang_a, rad_a], axis=1), np.stack([tang_b, rad_b], axis=1)


def odometry(
    theta: ArrayLike,
    r: ArrayLike,
    dtheta_dt: ArrayLike,
    dr_dt: ArrayLike | None = None,
    *,
    radial_weight: float = 1.0,
    residual_threshold: float | None = None,
    trials: int = 500,
    loss: str = "soft_l1",
    seed: int = 0,
) -> OdometryFit:
    """Fit the robot's yaw rate and velocity to the flow of many points.

    Robust in two steps. (1) Least median of squares over ``trials`` random
    minimal samples (solved in one batch): the hypothesis with the smallest
    median point residual wins, which tolerates up to half the points moving
    on their own; its median gives a robust residual scale ``sigma``.
    (2) Points within ``residual_threshold`` (default ``2.5 sigma``) are the
    inliers; the model is refined on them with
    :func:`scipy.optimize.least_squares` (robust ``loss``, ``f_scale = sigma``),
    and the inliers are recomputed with the refined model.

    Parameters
    ----------
    theta, r, dtheta_dt : ndarray, shape (N,)
        Bearing (rad), range (m) and bearing rate (rad/frame) of each point.
    dr_dt : ndarray, shape (N,), optional
        Radial velocity (m/frame). Omni flow's radial component is the noisier
        one; leave it out (or lower ``radial_weight``) to fit on the bearing
        rates alone, which then need bearings spread around the axis.
    radial_weight : float
        Weight of the dr/dt rows against the r dtheta/dt rows (both m/frame).
    residual_threshold : float, optional
        Inlier threshold on a point's RMS residual, m/frame.
    trials : int
        Random minimal samples for step (1).
    loss : str
        Robust loss of the refinement (``"linear"`` for plain least squares).
    seed : int
        Seed of the sampling.

    Returns
    -------
    OdometryFit

    Raises
    ------
    ValueError
        Too few points with finite data, or points that cannot separate the
        three unknowns (e.g. all at one bearing).
    """
    from scipy.optimize import least_squares

    use_radial = dr_dt is not None and radial_weight > 0
    theta, r, dtheta_dt = (np.asarray(a, dtype=float).ravel() for a in (theta, r, dtheta_dt))
    dr = np.asarray(dr_dt, dtype=float).ravel() if use_radial else np.zeros_like(r)
    n = r.size
    if not (theta.size == n == dtheta_dt.size == dr.size):
        raise ValueError("odometry: theta, r, dtheta_dt (and dr_dt) must have equal lengths")
    ok = np.isfinite(theta) & np.isfinite(r) & np.isfinite(dtheta_dt) & np.isfinite(dr) & (r > 0)
    A, b = _odometry_rows(theta, r, dr, dtheta_dt, radial_weight if use_radial else 0.0)
    k = A.shape[1]
    m = 2 if k == 2 else 3  # points per minimal sample (2 x 2 rows or 3 x 1 row for 3 unknowns)
    idx = np.flatnonzero(ok)
    if idx.size < m + 1:
        raise ValueError(f"odometry: {idx.size} point(s) with finite data; need at least {m + 1}")
    Ao, bo = A[idx].reshape(-1, k, 3), b[idx]
    if np.linalg.matrix_rank(Ao.reshape(-1, 3)) < 3:
        raise ValueError(
            "odometry: the points cannot separate yaw rate and velocity (all at one bearing?)"
        )

    # (1) least median of squares over random minimal samples, solved in batches.
    rng = np.random.default_rng(seed)
    samples = rng.integers(0, idx.size, size=(4 * trials, m))
    samples.sort(axis=1)
    samples = samples[np.all(np.diff(samples, axis=1) > 0, axis=1)][:trials]
    As = Ao[samples].reshape(len(samples), m * k, 3)
    bs = bo[samples].reshape(len(samples), m * k)
    with np.errstate(all="ignore"):
        AtA = np.einsum("tij,tik->tjk", As, As)
        Atb = np.einsum("tij,ti->tj", As, bs)
        cond = np.linalg.cond(AtA)
        good = np.isfinite(cond) & (cond < 1e10)
        params = np.full((len(samples), 3), np.nan)
        params[good] = np.linalg.solve(AtA[good], Atb[good][..., None])[..., 0]
        med = np.full(len(samples), np.inf)
        block = max(1, 2_000_000 // (idx.size * k))  # bound the (trials, N, k) residual array
        for lo in range(0, len(samples), block):
            res = np.einsum("nkj,tj->tnk", Ao, params[lo : lo + block]) - bo[None]
            med[lo : lo + block] = np.median(np.sqrt(np.mean(res**2, axis=2)), axis=1)
    med = np.where(good, med, np.inf)
    best = int(np.argmin(med))
    if not np.isfinite(med[best]):
        raise ValueError("odometry: no well-conditioned sample; the points' bearings are too alike")
    p_dof = 3.0 / k  # unknowns per point-equivalent
    sigma = 1.4826 * (1.0 + 5.0 / max(idx.size - p_dof, 1.0)) * float(med[best])
    tiny = 1e-12 * max(1.0, float(np.max(np.abs(bo))))
    sigma = max(sigma, tiny)
    threshold = float(residual_threshold) if residual_threshold is not None else 2.5 * sigma
    best_res = np.sqrt(np.mean((np.einsum("nkj,j->nk", Ao, params[best]) - bo) ** 2, axis=1))
    inl = best_res <= threshold
    if inl.sum() < m + 1:
        inl = best_res <= np.partition(best_res, m)[m]

    # (2) refine on the inliers with a robust loss, then recompute the inliers.
    def fun(p, A_, b_):
        return (A_ @ p - b_).ravel()

    Ai, bi = Ao[inl].reshape(-1, 3), bo[inl].ravel()
    sol = least_squares(fun, params[best], args=(Ai, bi), loss=loss, f_scale=sigma)
    w, vx, vy = sol.x
    all_res = np.full(n, np.inf)
    all_res[idx] = np.sqrt(np.mean((np.einsum("nkj,j->nk", Ao, sol.x) - bo) ** 2, axis=1))
    inliers = all_res <= threshold
    return OdometryFit(
        float(w), float(vx), float(vy), inliers, all_res, float(sigma), float(threshold)
    )
