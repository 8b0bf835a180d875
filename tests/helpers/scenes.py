"""Closed-form scenes and truth helpers for the matching, flow and pipeline tests.

The rig is the paper's geometry (d = 0.10 m, R = 0.05 m, s = 0.30 m). The wall
texture is one the rig resolves along radial lines: fine detail up the wall,
coarse around it (see :func:`striped_wall`).
"""

from __future__ import annotations

import cv2
import numpy as np

from omniflow.geometry.rig import Rig, Unit
from omniflow.matching import Matches
from omnisim.synthetic import Cylinder, Motion, SyntheticScene, Texture


def paper_rig(size: int = 256) -> Rig:
    return Rig.symmetric(d=0.10, R=0.05, s=0.30, size=size)


def turning_wall_scene(rig: Rig, yaw: float) -> SyntheticScene:
    """A randomly textured wall (r = 2 m) turning about the rig's axis at ``yaw`` rad per
    frame in front of the still rig: tangential flow h_i yaw, no radial flow."""
    texture = Texture.random(3, contrast=0.4, mean=0.5, period_u=4 * np.pi)
    wall = Cylinder(radius=2.0, id=1, name="wall", texture=texture, motion=Motion(yaw_rate=yaw))
    return SyntheticScene(rig=rig, bodies=(wall,))


def asymmetric_rig(size: int = 256) -> Rig:
    """Units with different image centres and rim radii (so v_1 != v_2)."""
    c = size / 2
    cam1 = Unit(d=0.1, R=0.05, x_c=c + 1.3, y_c=c - 0.7, r_m=c - 3, width=size, height=size,
                tip_h=0.3, name="cam1")  # fmt: skip
    cam2 = Unit(d=0.1, R=0.05, x_c=c - 2.1, y_c=c + 1.6, r_m=c - 8, width=size, height=size,
                tip_h=0.0, name="cam2")  # fmt: skip
    rig = Rig(cam1=cam1, cam2=cam2, s=0.3)
    rig.validate()
    return rig


def striped_wall(radius: float, seed: int, *, n: int = 16, contrast: float = 0.8) -> Texture:
    """A wall texture the rig resolves: fine detail up the wall, coarse around it.

    Wavelengths 0.03-0.3 m in height; around the wall at least 1 m (whole
    cycles per circumference). Near the image centre cam1 sees h_2/h_1 times
    less of the wall per pixel tangentially than cam2, so fine tangential
    detail cannot be matched along radial lines.
    """
    rng = np.random.default_rng(seed)
    fv = np.exp(rng.uniform(np.log(1 / 0.3), np.log(1 / 0.03), n)) * rng.choice([-1, 1], n)
    circ = 2 * np.pi * radius
    kmax = max(1, int(circ / 1.0))
    fu = rng.integers(-kmax, kmax + 1, n) / circ
    amp = rng.uniform(0.5, 1.0, n)
    amp *= contrast / amp.sum()
    return Texture(fu=fu, fv=fv, amp=amp, phase=rng.uniform(0, 2 * np.pi, n), mean=0.5)


def wall_scene(
    rig: Rig,
    radius: float = 2.0,
    seed: int = 3,
    robot: Motion | None = None,
    wall_motion: Motion | None = None,
) -> SyntheticScene:
    """A textured vertical wall around the rig (no floor or ceiling)."""
    wall = Cylinder(radius=radius, id=1, name="wall", texture=striped_wall(radius, seed),
                    motion=wall_motion or Motion())  # fmt: skip
    return SyntheticScene(rig=rig, bodies=(wall,), robot=robot or Motion())


def frames(scene: SyntheticScene, count: int = 3) -> tuple[np.ndarray, np.ndarray]:
    return (scene.frames("cam1", count, dtype=np.float32),
            scene.frames("cam2", count, dtype=np.float32))  # fmt: skip


def true_h_other(scene: SyntheticScene, h1: np.ndarray, theta: np.ndarray, t: int = 0):
    """cam2's image radius of what cam1 sees at (h1, theta), and whether cam2 sees it."""
    rig = scene.rig
    hit = scene.trace(rig.cam1, t, h1, theta)
    h2 = rig.cam2.image_radius(hit.r, hit.Z)
    seen = np.isfinite(hit.r) & scene._sees(rig.cam2, t, hit.r, theta, hit.Z, hit.index)
    return h2, seen


def true_matches(scene: SyntheticScene, *, h_min: float = 16.0, rim_margin: float = 4.0):
    """True stereo matches at cam1's pixel centres seen by both units at t = 0 and 1.

    Returns (Matches, truth dict of cam1 at frame 0, selection mask (H, W)).
    """
    rig = scene.rig
    gt = scene.truth("cam1", 0)
    x, y = rig.cam1.pixel_centres()
    h1, theta = rig.cam1.polar_of_pixel(x, y)
    with np.errstate(invalid="ignore"):
        sel = (
            (gt["gt.stereo.valid"] > 0)
            & (gt["gt.flow.valid"] > 0)
            & (h1 > h_min)
            & (gt["gt.stereo.h_other"] < rig.cam2.r_m - rim_margin)
        )
    m = Matches.from_polar(rig, theta[sel], h1[sel], gt["gt.stereo.h_other"][sel])
    return m, gt, sel


def to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(image) * 255.0), 0, 255).astype(np.uint8)


def dis_flow(frame0: np.ndarray, frame1: np.ndarray) -> np.ndarray:
    """OpenCV DIS (medium preset) on the 8-bit frames, (H, W, 2) pixels."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(to_uint8(frame0), to_uint8(frame1), None)


def band_scene(rig: Rig, *, yaw: float = 0.01, band_mean: float = 0.25) -> SyntheticScene:
    """A motion boundary the range test cannot see: a band turning in front of a wall.

    The band is a short coaxial cylinder (r = 1.85 m, 0.40 <= Z <= 0.55 m, id 2, texture
    mean ``band_mean``, contrast 0.2) turning about the rig's axis at ``yaw`` rad per
    frame; the wall (r = 2.0 m, id 1, mean 0.5, contrast 0.4) is static, as is the rig.
    Their ranges differ by 7.5 %, inside the default ``pool_range_tol``.
    """
    band = Cylinder(radius=1.85, id=2, name="band", z_min=0.40, z_max=0.55,
                    texture=Texture.random(5, contrast=0.2, mean=band_mean,
                                           period_u=2 * np.pi * 1.85),
                    motion=Motion(yaw_rate=yaw))  # fmt: skip
    wall_texture = Texture.random(3, contrast=0.4, mean=0.5, period_u=4 * np.pi)
    wall = Cylinder(radius=2.0, id=1, name="wall", texture=wall_texture)
    return SyntheticScene(rig=rig, bodies=(band, wall))


def sparse_true_matches(scene: SyntheticScene, share: float, seed: int = 0):
    """:func:`true_matches` at a seeded random ``share`` of the pixels (a matcher's density).

    Returns (Matches, truth dict of cam1 at frame 0).
    """
    m, gt, _ = true_matches(scene)
    keep = np.random.default_rng(seed).random(len(m.theta)) < share
    return Matches.from_polar(scene.rig, m.theta[keep], m.h1[keep], m.h2[keep]), gt


def wall_under_gain_field(wall: Motion, amp: float, **knobs):
    """The wall scene (robot still, the wall moving by ``wall``) with frame t + 1 of both
    units times 1 + ``amp`` sin(2 theta), a brightness change varying across the image,
    solved by ``estimate()`` at 3 % of the true matches with ``OmniFlowConfig(**knobs)``.

    Returns (result, cam1 endpoint error per point, true cam1 radial flow dh per point).
    """
    from omniflow.config import OmniFlowConfig
    from omniflow.pipeline import estimate

    rig = paper_rig(256)
    scene = wall_scene(rig, wall_motion=wall)
    f1, f2 = frames(scene, 2)
    m, gt = sparse_true_matches(scene, 0.03)
    gains = []
    for cam in (rig.cam1, rig.cam2):
        _, theta = cam.polar_of_pixel(*cam.pixel_centres())
        gains.append((1.0 + amp * np.sin(2.0 * theta)).astype(np.float32))
    res = estimate([f1[0], f1[1] * gains[0]], [f2[0], f2[1] * gains[1]], rig,
                   OmniFlowConfig(**knobs), matches=m)  # fmt: skip
    iy, ix = res["y"].astype(int), res["x"].astype(int)  # true matches: pixel centres
    dh, hdtheta = gt["gt.flow.dh"][iy, ix], gt["gt.flow.hdtheta"][iy, ix]
    err = np.hypot(res["dh1_dt"] - dh, res["h1"] * res["dtheta_dt"] - hdtheta)
    return res, err, dh
