"""A closed-form image of the test card: every pixel's traced ray met with the tube.

Each pixel is split into ``ss`` x ``ss`` sub-pixels; each sub-pixel's reflected ray
(:func:`omniflow.geometry.rig_errors.traced_rays`) meets the card's tube, and the check
there (:meth:`TestCard.dark`) gives 0.1 (dark) or 0.5 (light); outside the mirror 0.
The pixel is the mean: the box filter of an exact area coverage, to 1 / ss^2.
"""

from __future__ import annotations

import numpy as np

from omniflow.geometry.rig_errors import UnitErrors, traced_rays
from omniflow.geometry.test_card import TestCard

DARK, LIGHT = 0.1, 0.5


def card_image(unit, card: TestCard, errors: UnitErrors | None = None, ss: int = 4) -> np.ndarray:
    """The card seen by ``unit`` with ``errors`` (None: ideal), (H, W) float64."""
    off = (np.arange(ss) + 0.5) / ss
    xs = (np.arange(unit.width)[:, None] + off[None, :]).ravel()
    ys = (np.arange(unit.height)[:, None] + off[None, :]).ravel()
    x, y = np.meshgrid(xs, ys)
    o, w, ok, _ = traced_rays(unit, x, y, errors or UnitErrors())
    c = np.asarray(card.center)
    p = o[..., :2] - c[:2]
    a = (w[..., :2] ** 2).sum(-1)
    b = (p * w[..., :2]).sum(-1)
    cc = (p**2).sum(-1) - card.radius**2
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b + np.sqrt(b * b - a * cc)) / a
        hit = o + t[..., None] * w
        theta = np.arctan2(hit[..., 1] - c[1], hit[..., 0] - c[0])
        on = ok & np.isfinite(t) & (np.abs(hit[..., 2] - c[2]) < card.height / 2)
        val = np.where(card.dark(np.mod(theta, 2 * np.pi), hit[..., 2]), DARK, LIGHT)
    img = np.where(on, val, 0.0)
    return img.reshape(unit.height, ss, unit.width, ss).mean(axis=(1, 3))
