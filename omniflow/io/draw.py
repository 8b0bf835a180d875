"""Pictures of flow: the Middlebury colour coding and arrows over an image.

Generic over where the flow lives: a dense field ``(H, W)`` with an optional
validity mask, or scattered points ``x, y`` (continuous pixel coordinates,
pixel centres at ``j + 0.5`` as in :mod:`omniflow.conventions`) with their
vectors ``dx, dy`` in pixels. Every function returns an RGB ``uint8`` image
``(H, W, 3)``; save it with :func:`omniflow.io.imageio.write_png` (``bits=8``).

Colour coding (Baker et al., "A Database and Evaluation Methodology for Optical
Flow", IJCV 2011): hue gives the direction, saturation the magnitude relative
to ``max_flow``; white is no motion, black is unknown. Flow along +x is red,
along +y (down on screen) orange-yellow, along -x cyan-blue, exactly as the
Middlebury ``flowToColor`` code, so pictures compare with the flow literature.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.io.imageio import to_grey, to_uint8

__all__ = [
    "color_wheel",
    "draw_flow_arrows",
    "draw_flow_points",
    "flow_to_color",
    "grey_background",
]

# Middlebury colour wheel: hue steps between the six primaries (RY, YG, GC, CB, BM, MR).
_WHEEL_STEPS = (15, 6, 4, 11, 13, 6)


def _make_wheel() -> NDArray[np.float64]:
    ry, yg, gc, cb, bm, mr = _WHEEL_STEPS
    cols = []
    cols += [(255, 255 * i / ry, 0) for i in range(ry)]
    cols += [(255 - 255 * i / yg, 255, 0) for i in range(yg)]
    cols += [(0, 255, 255 * i / gc) for i in range(gc)]
    cols += [(0, 255 - 255 * i / cb, 255) for i in range(cb)]
    cols += [(255 * i / bm, 0, 255) for i in range(bm)]
    cols += [(255, 0, 255 - 255 * i / mr) for i in range(mr)]
    return np.asarray(cols, dtype=np.float64) / 255.0


_WHEEL = _make_wheel()


def flow_to_color(
    dx: ArrayLike,
    dy: ArrayLike,
    *,
    max_flow: float | None = None,
    mask: ArrayLike | None = None,
) -> NDArray[np.uint8]:
    """Middlebury colour of each flow vector.

    Parameters
    ----------
    dx, dy : ndarray, any equal shapes (dense (H, W) or scattered (N,))
        Flow in pixels, x to the right and y down.
    max_flow : float, optional
        Magnitude drawn fully saturated; larger vectors are darkened (x 0.75).
        Default: the largest finite magnitude (1 if all are zero).
    mask : ndarray of bool, optional
        False where the flow is unknown; those entries (and non-finite flow)
        are black.

    Returns
    -------
    ndarray, shape dx.shape + (3,), uint8, RGB
    """
    u = np.asarray(dx, dtype=np.float64)
    v = np.asarray(dy, dtype=np.float64)
    if u.shape != v.shape:
        raise ValueError(f"flow_to_color: dx {u.shape} and dy {v.shape} differ in shape")
    known = np.isfinite(u) & np.isfinite(v)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != u.shape:
            raise ValueError(f"flow_to_color: mask {m.shape} does not match flow {u.shape}")
        known &= m
    u = np.where(known, u, 0.0)
    v = np.where(known, v, 0.0)
    mag = np.hypot(u, v)
    if max_flow is None:
        max_flow = float(mag[known].max()) if known.any() else 1.0
    if not max_flow > 0:
        max_flow = 1.0
    rad = mag / max_flow
    ncols = len(_WHEEL)
    angle = np.arctan2(-v, -u) / np.pi  # in (-1, 1], as Middlebury's flowToColor
    fk = (angle + 1.0) / 2.0 * (ncols - 1)
    k0 = np.floor(fk).astype(int) % ncols
    k1 = (k0 + 1) % ncols
    f = (fk - np.floor(fk))[..., None]
    col = (1 - f) * _WHEEL[k0] + f * _WHEEL[k1]
    inside = (rad <= 1)[..., None]
    col = np.where(inside, 1 - rad[..., None] * (1 - col), col * 0.75)
    col = np.where(known[..., None], col, 0.0)
    return np.rint(np.clip(col, 0, 1) * 255).astype(np.uint8)


def color_wheel(size: int = 64) -> NDArray[np.uint8]:
    """The colour key: ``flow_to_color`` of a disc of flows up to radius ``size / 2``."""
    c = (np.arange(size) + 0.5) - size / 2.0
    u, v = np.meshgrid(c, c)
    inside = np.hypot(u, v) <= size / 2.0
    return flow_to_color(u, v, max_flow=size / 2.0, mask=inside)


def grey_background(image: ArrayLike, *, dim: float = 1.0) -> NDArray[np.uint8]:
    """An image as an RGB uint8 background: grey (or colour) stretched 1st-99th percentile.

    ``dim`` < 1 darkens it so drawings on top stand out.
    """
    arr = np.asarray(image, dtype=np.float32)
    if arr.ndim == 3 and arr.shape[2] == 3:
        base = to_uint8(arr, lo=None, hi=None)
    else:
        g = to_uint8(to_grey(arr), lo=None, hi=None)
        base = np.repeat(g[:, :, None], 3, axis=2)
    if dim != 1.0:
        base = np.rint(base * float(dim)).astype(np.uint8)
    return np.ascontiguousarray(base)


def _points(x, y, dx, dy):
    arrs = [np.ravel(np.asarray(a, dtype=np.float64)) for a in (x, y, dx, dy)]
    n = {a.size for a in arrs}
    if len(n) != 1:
        raise ValueError(f"x, y, dx, dy must have equal sizes, got {[a.size for a in arrs]}")
    ok = np.all([np.isfinite(a) for a in arrs], axis=0)
    return [a[ok] for a in arrs]


def draw_flow_arrows(
    image: ArrayLike,
    x: ArrayLike,
    y: ArrayLike,
    dx: ArrayLike,
    dy: ArrayLike,
    *,
    scale: float | None = None,
    max_arrows: int | None = None,
    color: tuple[int, int, int] | None = None,
    thickness: int = 1,
    legend: bool = True,
    seed: int = 0,
) -> NDArray[np.uint8]:
    """Arrows from each point ``(x, y)`` along ``scale * (dx, dy)`` over the image.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        Background (stretched to its 1st-99th percentile, dimmed).
    x, y : ndarray, shape (N,)
        Arrow tails, continuous pixel coordinates (centre of pixel (i, j) at
        x = j + 0.5, y = i + 0.5).
    dx, dy : ndarray, shape (N,)
        Flow in pixels.
    scale : float, optional
        Drawing magnification. Default: the 95th percentile magnitude is drawn
        3 % of the image's larger side long. Written in the legend.
    max_arrows : int, optional
        At most this many arrows (a seeded random subset) so the picture stays
        readable. Default: one per 200 pixels of the image (at least 50).
    color : (r, g, b), optional
        One colour for all arrows. Default: each arrow in its Middlebury colour.
    legend : bool
        Write the scale and arrow count in the top-left corner.

    Returns
    -------
    ndarray, shape (H, W, 3), uint8, RGB
    """
    import cv2

    canvas = grey_background(image, dim=0.8)
    x, y, dx, dy = _points(x, y, dx, dy)
    mag = np.hypot(dx, dy)
    if scale is None:
        p95 = float(np.percentile(mag, 95)) if mag.size else 0.0
        scale = 0.03 * max(canvas.shape[:2]) / p95 if p95 > 0 else 1.0
    if max_arrows is None:
        max_arrows = max(50, canvas.shape[0] * canvas.shape[1] // 200)
    if x.size > max_arrows:
        keep = np.random.default_rng(seed).choice(x.size, max_arrows, replace=False)
        x, y, dx, dy, mag = x[keep], y[keep], dx[keep], dy[keep], mag[keep]
    colours = (
        np.tile(np.asarray(color, dtype=np.uint8), (x.size, 1))
        if color is not None
        else flow_to_color(dx, dy, max_flow=float(mag.max()) if mag.size else 1.0)
    )
    shift = 4  # OpenCV sub-pixel drawing: coordinates in 1/16 px
    f = float(1 << shift)
    tail_x = np.rint((x - 0.5) * f).astype(int)  # pixel centre j + 0.5 -> index j
    tail_y = np.rint((y - 0.5) * f).astype(int)
    head_x = np.rint((x - 0.5 + scale * dx) * f).astype(int)
    head_y = np.rint((y - 0.5 + scale * dy) * f).astype(int)
    for i in range(x.size):
        length = scale * mag[i]
        c = tuple(int(k) for k in colours[i])
        if length < 1.0:
            cv2.circle(canvas, (tail_x[i], tail_y[i]), 1 << shift, c, -1, cv2.LINE_AA, shift)
            continue
        tip = min(0.4, 4.0 / length)
        cv2.arrowedLine(
            canvas,
            (tail_x[i], tail_y[i]),
            (head_x[i], head_y[i]),
            c,
            thickness,
            cv2.LINE_AA,
            shift,
            tip,
        )
    if legend:
        _legend(canvas, f"{x.size} arrows, drawn x{scale:.3g}")
    return canvas


def draw_flow_points(
    image: ArrayLike,
    x: ArrayLike,
    y: ArrayLike,
    dx: ArrayLike,
    dy: ArrayLike,
    *,
    max_flow: float | None = None,
    radius: int = 1,
    key: bool = True,
) -> NDArray[np.uint8]:
    """Scattered flow as dots in the Middlebury colour over a dimmed image.

    ``max_flow`` as in :func:`flow_to_color` (default: the 99th percentile
    magnitude); ``key`` puts the colour wheel in the top-right corner.
    """
    import cv2

    canvas = grey_background(image, dim=0.5)
    x, y, dx, dy = _points(x, y, dx, dy)
    mag = np.hypot(dx, dy)
    if max_flow is None:
        max_flow = float(np.percentile(mag, 99)) if mag.size else 1.0
    colours = flow_to_color(dx, dy, max_flow=max_flow)
    h, w = canvas.shape[:2]
    cols = np.floor(x).astype(int)
    rows = np.floor(y).astype(int)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    if radius <= 0:
        canvas[rows[inside], cols[inside]] = colours[inside]
    else:
        for r, c, col in zip(rows[inside], cols[inside], colours[inside], strict=True):
            cv2.circle(canvas, (int(c), int(r)), radius, tuple(int(k) for k in col), -1)
    if key:
        size = max(16, min(h, w) // 6)
        canvas[2 : 2 + size, w - 2 - size : w - 2] = np.where(
            color_wheel(size).any(axis=2, keepdims=True),
            color_wheel(size),
            canvas[2 : 2 + size, w - 2 - size : w - 2],
        )
        _legend(canvas, f"{x.size} points, saturated at {max_flow:.3g} px")
    return canvas


def _legend(canvas: NDArray[np.uint8], text: str) -> None:
    """White text in the top-left corner on a black box, readable over any picture
    (an outline alone is lost over bright texture at the smallest font)."""
    import cv2

    h = canvas.shape[0]
    font, font_scale = cv2.FONT_HERSHEY_SIMPLEX, max(0.3, h / 1400.0)
    y = int(6 + 18 * font_scale)
    (tw, th), base = cv2.getTextSize(text, font, font_scale, 1)
    canvas[max(0, y - th - 3) : y + base + 2, : 4 + tw + 3] = 0
    cv2.putText(canvas, text, (4, y), font, font_scale, (255, 255, 255), 1, cv2.LINE_AA)
