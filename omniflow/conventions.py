"""Coordinate conventions, written once for the whole project.

Every module of ``omniflow``, ``omnisim`` and ``validation`` follows this page;
the README repeats it.

Rig frame (metres)
    Right-handed (X, Y, Z). Z runs up the common axis of the two mirrors. The
    origin is the tip of cam2's cone (the lower unit). cam1's tip is at Z = s.
    Both cameras sit below their mirrors on the axis, looking up (+Z) at a
    90-degree cone whose tip points down at them; camera i's centre is at
    Z = tip_h - d.

Cylindrical scene coordinates (r, theta, h)
    r = hypot(X, Y) >= 0, distance from the axis, metres.
    theta = atan2(Y, X), radians in [-pi, pi): azimuth from +X towards +Y
    (counter-clockwise seen from above).
    h = Z, metres, measured from cam2's tip (eq. 4). Unit 1 sees h - s (eq. 3).

Pixels
    Pixel (row i, col j) covers [j, j+1) x [i, i+1); its centre is at
    x = j + 0.5, y = i + 0.5. x grows to the right (columns), y downwards
    (rows). The image centre (x_c, y_c) and the rim radius r_m are in these
    continuous coordinates, so a 512 x 512 image with the axis in the middle
    has x_c = y_c = 256.0. With this choice the DCT basis of eq. (17)-(18)
    is cos(pi p x / X) with no extra half-pixel shift.

Camera mounting
    Image x runs along rig +X and image y along rig +Y (a camera looking up
    +Z; a proper rotation, not a mirror flip of the camera itself). Hence the
    polar image angle theta_i = atan2(y - y_c, x - x_c) equals the scene
    azimuth theta exactly, with no offset; on screen (y down) theta grows
    clockwise. h_i = hypot(x - x_c, y - y_c) is the image radius in pixels.

Time and flow
    Time is counted in frame intervals. Flow is the displacement from frame t
    to frame t+1 of the image of the same material point: (dx, dy) in pixels,
    next position minus this position. Polar flow is (dh_i, h_i dtheta_i):
    the radial and tangential components in pixels, with dtheta wrapped to
    [-pi, pi) and h_i taken at frame t. Velocities are per frame interval
    (pixels/frame, radians/frame, metres/frame); multiply by 1/frame_interval
    for seconds.

Images
    Grey images are float arrays, shape (H, W), indexed [row, col]. Colour
    inputs are reduced to luminance with Rec. 709 weights
    (``omniflow.io.imageio.to_grey``, :data:`LUMA_WEIGHTS`). Radiance is linear.

JSON
    A number JSON cannot hold (NaN, +inf, -inf) is written as null, in every
    file the project writes (``omniflow.io.jsonio.jsonable``).
"""

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Rec. 709 luminance weights applied to linear RGB.
LUMA_WEIGHTS = (0.2126, 0.7152, 0.0722)


def wrap_angle(angle: ArrayLike) -> NDArray:
    """Wrap angles (radians) to the convention's interval [-pi, pi)."""
    return (np.asarray(angle, dtype=float) + np.pi) % (2 * np.pi) - np.pi
