"""Omni flow: the polar flow equation and its coaxial solutions (paper section 4).

Notation (per stereo match at azimuth theta, cam1 radius h_1, cam2 radius h_2):
f_h = df/dh_i (grey levels per pixel), f_theta = df/dtheta (grey levels per
radian, no 1/h_i factor), f_t = df/dt (grey levels per frame), for image 1
(``f1_*``) and image 2 (``f2_*``). Unknowns a = dh_1/dt (pixels per frame) and
b = dtheta/dt (radians per frame); theta_1 = theta_2 for a coaxial rig.

The flow equation, eq. (8), with v = (dh_i/dt, h_i dtheta/dt) and
grad f = (f_h, f_theta / h_i)::

    f_h dh_i/dt + f_theta dtheta/dt + f_t = 0                   # eq. (8)

Coaxial pair, eq. (9) and (15), with dh_2 = (h_2 / h_1) dh_1 (eq. 14, exact
only when the scene point does not move along the axis)::

    f1_h a             + f1_theta b = -f1_t                     # eq. (9)
    (h_2/h_1) f2_h a   + f2_theta b = -f2_t                     # eq. (15)
    D = f1_h f2_theta - (h_2/h_1) f2_h f1_theta                 # eq. (16)
    a = (f2_t f1_theta - f1_t f2_theta) / D
    b = ((h_2/h_1) f2_h f1_t - f1_h f2_t) / D

Why the radial component is ill-conditioned: both units see nearly the same
patch at the same scale, so f2_h ~ f1_h and f2_theta ~ f1_theta; then
D ~ f_h f_theta (1 - h_2/h_1) and a ~ -(f2_t - f1_t) / (f_h (h_2/h_1 - 1)):
the radial flow rests on the small difference of the two temporal
derivatives. :func:`omniflow.solve.pooled.pooled_solution` stacks eq. (9) and (15) of the matched
points in a small neighbourhood and solves them in least squares (a polar
Lucas-Kanade over both units), which does not need that difference.

Confidence. Every solver reports, per point, lambda_min / lambda_max of the
normal matrix A^T A of its (scaled) system, in [0, 1]: 1 is perfectly
conditioned, 0 singular. The columns are scaled to pixels per frame
(a, h_1 b) so the measure does not depend on units. For the 2x2 direct
solution this is 1 / cond(A)^2.

When the scene point moves along the axis with dh/dt != 0, differentiating
eq. (3)-(4) gives dh_2 - (h_2/h_1) dh_1 = s v dh / ((d + r)(s - h)) (see
:func:`axial_motion_violation`), and eq. (15) is off by f2_h times that;
:func:`predicted_bias` gives the resulting error of the solution.

Range rate, eq. (11) and (13): :func:`radial_velocity` gives dr/dt from cam1's
radial flow, :func:`radial_velocity_stereo` from both units' without eq. (14).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "axial_motion_violation",
    "conditioning",
    "determinant",
    "direct_solution",
    "eig_ratio",
    "flow_residual",
    "partial_solutions",
    "predicted_bias",
    "radial_velocity",
    "radial_velocity_stereo",
]


def _arr(*values: ArrayLike) -> list[NDArray]:
    out = [np.asarray(v, dtype=np.float64) for v in values]
    shape = np.broadcast_shapes(*(o.shape for o in out))
    return [np.broadcast_to(o, shape) for o in out]


def flow_residual(
    f_h: ArrayLike, f_theta: ArrayLike, f_t: ArrayLike, dh_dt: ArrayLike, dtheta_dt: ArrayLike
) -> NDArray:
    """Left side of eq. (8): f_h dh_i/dt + f_theta dtheta/dt + f_t (0 for an exact flow)."""
    f_h, f_theta, f_t, dh_dt, dtheta_dt = _arr(f_h, f_theta, f_t, dh_dt, dtheta_dt)
    return f_h * dh_dt + f_theta * dtheta_dt + f_t


def partial_solutions(
    f_h: ArrayLike, f_theta: ArrayLike, f_t: ArrayLike, h: ArrayLike, *, rel_tol: float = 0.1
) -> tuple[NDArray, NDArray]:
    """The partial solutions of eq. (8) for one unit (section 4).

    Where the tangential gradient vanishes (|f_theta / h_i| <= rel_tol |f_h|),
    dh_i/dt = -f_t / f_h; where the radial gradient vanishes
    (|f_h| <= rel_tol |f_theta / h_i|), dtheta/dt = -f_t / f_theta.

    Parameters
    ----------
    f_h, f_theta, f_t : array_like
        Polar gradient (eq. 19-20) and time derivative at the points.
    h : array_like
        Image radius h_i of the points, pixels.
    rel_tol : float
        How small the other component must be, relative.

    Returns
    -------
    dh_dt, dtheta_dt : ndarray
        NaN where the respective condition does not hold.
    """
    f_h, f_theta, f_t, h = _arr(f_h, f_theta, f_t, h)
    g_tan = np.abs(f_theta) / np.where(h > 0, h, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        radial = np.where((g_tan <= rel_tol * np.abs(f_h)) & (f_h != 0), -f_t / f_h, np.nan)
        tangential = np.where(
            (np.abs(f_h) <= rel_tol * g_tan) & (f_theta != 0), -f_t / f_theta, np.nan
        )
    return radial, tangential


def conditioning(
    f1_h: ArrayLike,
    f1_theta: ArrayLike,
    f2_h: ArrayLike,
    f2_theta: ArrayLike,
    h1: ArrayLike,
    h2: ArrayLike,
) -> NDArray:
    """Confidence of the direct solution: lambda_min / lambda_max of A^T A, in [0, 1].

    A is the 2x2 matrix of eq. (9) and (15) with the columns scaled to
    (dh_1/dt, h_1 dtheta/dt), i.e. rows (f1_h, f1_theta / h_1) and
    ((h_2/h_1) f2_h, f2_theta / h_1). Equal to 1 / cond(A)^2.
    """
    f1_h, f1_theta, f2_h, f2_theta, h1, h2 = _arr(f1_h, f1_theta, f2_h, f2_theta, h1, h2)
    k = h2 / h1
    a11, a12 = f1_h, f1_theta / h1
    a21, a22 = k * f2_h, f2_theta / h1
    m11 = a11 * a11 + a21 * a21
    m22 = a12 * a12 + a22 * a22
    m12 = a11 * a12 + a21 * a22
    return eig_ratio(m11, m12, m22)


def eig_ratio(m11: NDArray, m12: NDArray, m22: NDArray) -> NDArray:
    """lambda_min / lambda_max of symmetric 2x2 matrices [[m11, m12], [m12, m22]]."""
    tr = m11 + m22
    det = m11 * m22 - m12 * m12
    disc = np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    lmax = 0.5 * tr + disc
    lmin = np.maximum(0.5 * tr - disc, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(lmax > 0, lmin / lmax, 0.0)


def determinant(
    f1_h: ArrayLike, f1_theta: ArrayLike, f2_h: ArrayLike, f2_theta: ArrayLike,
    h1: ArrayLike, h2: ArrayLike,
) -> NDArray:  # fmt: skip
    """The determinant D of the coaxial system, eq. (16); ~0 where eq. (9) and (15) are
    nearly dependent."""
    f1_h, f1_theta, f2_h, f2_theta, h1, h2 = _arr(f1_h, f1_theta, f2_h, f2_theta, h1, h2)
    return f1_h * f2_theta - (h2 / h1) * f2_h * f1_theta  # eq. (16), with eq. (14)


def direct_solution(
    f1_h: ArrayLike,
    f1_theta: ArrayLike,
    f1_t: ArrayLike,
    f2_h: ArrayLike,
    f2_theta: ArrayLike,
    f2_t: ArrayLike,
    h1: ArrayLike,
    h2: ArrayLike,
) -> tuple[NDArray, NDArray, NDArray]:
    """The coaxial direct solution, eq. (16); NaN where D = 0.

    Parameters
    ----------
    f1_h, f1_theta, f1_t : array_like
        df1/dh_1, df1/dtheta, df1/dt at (h_1, theta) in image 1.
    f2_h, f2_theta, f2_t : array_like
        The same for image 2 at (h_2, theta).
    h1, h2 : array_like
        Matched image radii, pixels (h_2 > h_1 > 0).

    Returns
    -------
    dh1_dt : ndarray
        Radial flow in cam1, pixels per frame.
    dtheta_dt : ndarray
        Angular flow, radians per frame (the same in both units).
    D : ndarray
        The determinant of eq. (16).
    """
    f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t, h1, h2 = _arr(
        f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t, h1, h2
    )
    k = h2 / h1  # eq. (14)
    D = determinant(f1_h, f1_theta, f2_h, f2_theta, h1, h2)
    ok = D != 0
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(ok, (f2_t * f1_theta - f1_t * f2_theta) / D, np.nan)  # eq. (16)
        b = np.where(ok, (k * f2_h * f1_t - f1_h * f2_t) / D, np.nan)  # eq. (16)
    return a, b, D


def axial_motion_violation(
    r: ArrayLike, h: ArrayLike, dh_dt: ArrayLike, *, s: float, d: float, v: float
) -> NDArray:
    """dh_2 - (h_2/h_1) dh_1 caused by axial motion dh/dt (eq. 14's hidden assumption).

    Differentiating eq. (3)-(4) at fixed r: dh_2 - (h_2/h_1) dh_1 =
    s v dh / ((d + r)(s - h)), pixels per frame for dh_dt in metres per
    frame. Zero when the point does not move along the axis.
    """
    r, h, dh_dt = _arr(r, h, dh_dt)
    return s * v * dh_dt / ((d + r) * (s - h))


def predicted_bias(
    f1_h: ArrayLike,
    f1_theta: ArrayLike,
    f2_h: ArrayLike,
    f2_theta: ArrayLike,
    h1: ArrayLike,
    h2: ArrayLike,
    violation: ArrayLike,
) -> tuple[NDArray, NDArray]:
    """Error of the direct solution when eq. (14) is violated by ``violation`` px/frame.

    With the true dh_2 = (h_2/h_1) dh_1 + e, eq. (15) misses f2_h e on its
    right side, so the solution is off by A^-1 (0, f2_h e)::

        delta a = -f1_theta f2_h e / D,    delta b = f1_h f2_h e / D.

    Returns
    -------
    delta_dh1_dt, delta_dtheta_dt : ndarray
        Estimated minus true (for exact gradients and temporal derivatives).
    """
    f1_h, f1_theta, f2_h, f2_theta, h1, h2, e = _arr(
        f1_h, f1_theta, f2_h, f2_theta, h1, h2, violation
    )
    D = f1_h * f2_theta - (h2 / h1) * f2_h * f1_theta
    with np.errstate(divide="ignore", invalid="ignore"):
        return -f1_theta * f2_h * e / D, f1_h * f2_h * e / D


def radial_velocity(r: ArrayLike, h1: ArrayLike, dh1_dt: ArrayLike, *, d: float) -> NDArray:
    """dr/dt of scene points from their radial image flow in camera 1.

    ``dr/dt = -(d + r) (dh_1/dt) / h_1``: eq. (11) with eq. (13)
    (``dr/dh_i = -(d + r) / h_i`` at constant h).

    Parameters
    ----------
    r : ndarray
        Range from the axis, metres (from stereo, eq. 5).
    h1 : ndarray
        Image radius in camera 1, pixels.
    dh1_dt : ndarray
        Radial image flow in camera 1, pixels per frame.
    d : float
        Camera centre to cone tip, metres (``Rig.d``).

    Returns
    -------
    ndarray
        dr/dt in metres per frame (negative when approaching).
    """
    r, h1, dh1_dt = _arr(r, h1, dh1_dt)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -(d + r) * dh1_dt / h1


def radial_velocity_stereo(
    r: ArrayLike, h1: ArrayLike, h2: ArrayLike, dh1_dt: ArrayLike, dh2_dt: ArrayLike, *, d: float
) -> NDArray:
    """dr/dt from both units' radial flows, valid whatever the motion along the axis.

    Differentiating eq. (3) and (4), ``dr h_1 + (d + r) dh_1 = v dh`` and
    ``dr h_2 + (d + r) dh_2 = v dh``; their difference eliminates dh::

        dr/dt = -(d + r) (dh_2/dt - dh_1/dt) / (h_2 - h_1)

    With dh_2 = (h_2/h_1) dh_1 (eq. 14) this is :func:`radial_velocity`. It
    rests on the difference of the two radial flows, so it is noisier by
    about h_1 / (h_2 - h_1); use it only where eq. (14) does not hold.

    Parameters
    ----------
    r : ndarray
        Range from the axis, metres (eq. 5).
    h1, h2 : ndarray
        Image radii of the match in camera 1 and 2, pixels.
    dh1_dt, dh2_dt : ndarray
        Radial image flow in camera 1 and 2, pixels per frame.
    d : float
        Camera centre to cone tip, metres (``Rig.d``).

    Returns
    -------
    ndarray
        dr/dt in metres per frame (negative when approaching).
    """
    r, h1, h2, dh1_dt, dh2_dt = _arr(r, h1, h2, dh1_dt, dh2_dt)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -(d + r) * (dh2_dt - dh1_dt) / (h2 - h1)
