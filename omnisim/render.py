"""Render an omnisim Scene with Mitsuba 3 through the analytic cone-mirror sensor.

Public functions (docs/INTERFACES.md):

``render_camera(scene, frame, cam) -> float32 (H, W, 3)``
    Linear RGB radiance of one unit (``"cam1"`` or ``"cam2"``).
``render_frame(scene, frame) -> {cam: {channel: (H, W) float32}}``
    ``R``, ``G``, ``B`` and the ``gt.*`` channels of both cameras
    (:func:`omnisim.groundtruth.ground_truth`).

The Mitsuba scene of a Scene (meshes, materials, lights, the per-Scene cache
and the frame slots re-posed in place) is built by :mod:`omnisim.mitsuba_scene`,
shared with the ground truth (:mod:`omnisim.groundtruth`).

Integrator, spp, resolution, seed, variant and denoiser come from
``scene.render`` (``omnisim.mitsuba_scene._integrator_dict`` says what
``path`` and ``direct`` mean here). ``render.denoise = "oidn"`` renders the
albedo and shading normal of the first hit through the same film samples
(Mitsuba's ``aov`` integrator, same seed) and denoises the colour with Intel
Open Image Denoise guided by them (:mod:`omnisim.denoise`); docs/decisions/render.md
has the residual error and the time of each choice.

Determinism: the sampler seed of (frame, camera) is derived from the scene
seed (:func:`frame_seed`); with the same scene, seed and versions the images
are bit-identical, also across Dr.Jit thread counts (checked for 7, 9 and 16
spp with 1, 2 and 5 threads; ``tests/omnisim/test_render.py`` checks repeat renders).
The denoiser keeps it: Open Image Denoise on the CPU gave the same bytes in
two processes and with one Dr.Jit thread (default scene, 96 px, frame 1).
Also on a busy machine: ``tests/omnisim/test_same_bytes_under_load.py`` renders a
dataset twice under load and compares every file (docs/decisions/render_same_bytes.md).
"""

from __future__ import annotations

import hashlib
import time

import numpy as np
from numpy.typing import NDArray

from omnisim.denoise import GUIDE_SPP, oidn_denoise
from omnisim.exposure import average_subframes, subframe_offsets, subframe_spp
from omnisim.groundtruth import ground_truth_frame
from omnisim.mitsuba_scene import (
    CAMERAS,
    MitsubaFrame,
    MitsubaScene,
    camera_unit,
    clear_cache,
    get_mitsuba_scene,
    render_setting,
)
from omnisim.sensor import ensure_mitsuba

__all__ = [
    "CAMERAS",
    "MitsubaFrame",
    "MitsubaScene",
    "clear_cache",
    "frame_seed",
    "get_mitsuba_scene",
    "outside_rim",
    "render_camera",
    "render_exposure",
    "render_frame",
]


def frame_seed(seed: int, frame: int, cam: str) -> int:
    """Sampler seed (uint32) of one camera and frame, derived from the scene seed."""
    key = f"omnisim:{int(seed)}:{int(frame)}:{cam}".encode()
    return int.from_bytes(hashlib.sha256(key).digest()[:4], "little")


# ----------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------
def render_camera(
    scene,
    frame: int,
    cam: str,
    *,
    spp: int | None = None,
    seed: int | None = None,
    timings: dict[str, float] | None = None,
    guide_spp: int | None = None,
) -> NDArray[np.float32]:
    """Linear RGB radiance (H, W, 3) float32 of camera ``cam`` at ``frame``.

    ``spp`` and ``seed`` default to the scene's render settings; the sampler
    seed is :func:`frame_seed` of the scene seed, the frame and the camera.
    With ``render.denoise = "oidn"`` the guides (albedo, shading normal) are
    rendered with the same seed at ``min(spp, GUIDE_SPP)`` (then through the
    same film positions when spp <= GUIDE_SPP: the film sample is the
    sampler's first draw in both integrators) and the image is denoised
    (:func:`omnisim.denoise.oidn_denoise`); ``guide_spp`` overrides that
    number (benchmarks). ``timings``, if given, receives the seconds spent in
    ``render`` and ``denoise`` (guides included).
    """
    mi = ensure_mitsuba()
    ms = get_mitsuba_scene(scene)
    fr = ms.frame(frame)
    sensor = ms.sensor(cam, fr.robot_pose)
    u = camera_unit(scene, cam)
    spp = int(render_setting(scene, "spp", 16)) if spp is None else int(spp)
    base = int(render_setting(scene, "seed", 0)) if seed is None else int(seed)
    t0 = time.perf_counter()
    img = mi.render(
        fr.scene,
        sensor=sensor,
        integrator=ms.integrator,
        spp=spp,
        seed=frame_seed(base, frame, cam),
    )
    img = np.array(img, dtype=np.float32).reshape(u.height, u.width, 3)
    t1 = time.perf_counter()
    if ms.guides is not None:
        guides = mi.render(
            fr.scene,
            sensor=sensor,
            integrator=ms.guides,
            spp=min(spp, GUIDE_SPP) if guide_spp is None else int(guide_spp),
            seed=frame_seed(base, frame, cam),
        )
        guides = np.array(guides, dtype=np.float32).reshape(u.height, u.width, 6)
        img = oidn_denoise(img, guides, outside_rim(u))
    if timings is not None:
        timings["render"] = timings.get("render", 0.0) + t1 - t0
        if ms.guides is not None:
            timings["denoise"] = timings.get("denoise", 0.0) + time.perf_counter() - t1
    return img


def render_exposure(
    scene, frame: int, cam: str, *, timings: dict[str, float] | None = None
) -> NDArray[np.float32]:
    """:func:`render_camera` over the camera's open shutter (:mod:`omnisim.exposure`).

    With ``camera.shutter`` 0 (the default) this is ``render_camera(scene, frame, cam)``.
    Otherwise the mean of ``render.time_samples`` sub-frame renders, sub-frame j with
    the sampler seed of the scene seed's ``frame_seed(seed, j, "subframe")``.
    """
    shutter = float(getattr(getattr(scene, "camera", None), "shutter", 0.0))
    n = int(render_setting(scene, "time_samples", 1))
    offsets = subframe_offsets(shutter, n)
    if len(offsets) == 1:
        return render_camera(scene, frame, cam, timings=timings)
    spp = subframe_spp(int(render_setting(scene, "spp", 16)), len(offsets))
    base = int(render_setting(scene, "seed", 0))

    def sub(offset: float, j: int) -> NDArray[np.float32]:
        seed = frame_seed(base, j, "subframe")
        return render_camera(scene, frame + offset, cam, spp=spp, seed=seed, timings=timings)

    return average_subframes(sub, offsets)


def outside_rim(unit) -> NDArray[np.bool_]:
    """(H, W) pixels whose whole square lies outside the rim: no sample reaches the mirror."""
    x, y = unit.pixel_centres()
    # nearest point of the pixel square [x - 0.5, x + 0.5] x [y - 0.5, y + 0.5] to the centre
    nx = np.clip(unit.x_c, x - 0.5, x + 0.5) - unit.x_c
    ny = np.clip(unit.y_c, y - 0.5, y + 0.5) - unit.y_c
    return np.hypot(nx, ny) > unit.r_m


def render_frame(
    scene, frame: int, *, timings: dict[str, float] | None = None
) -> dict[str, dict[str, NDArray[np.float32]]]:
    """Both cameras' ``R``, ``G``, ``B`` and ``gt.*`` channels at ``frame``.

    ``timings``, if given, receives the seconds spent in ``render``,
    ``denoise`` (when the scene asks for a denoiser) and ``groundtruth``
    (summed over both cameras).
    """
    rgb = {cam: render_exposure(scene, frame, cam, timings=timings) for cam in CAMERAS}
    t1 = time.perf_counter()
    gt = ground_truth_frame(scene, frame, CAMERAS)
    t_gt = time.perf_counter() - t1
    out: dict[str, dict[str, NDArray[np.float32]]] = {}
    for cam in CAMERAS:
        chans = {c: np.ascontiguousarray(rgb[cam][..., i]) for i, c in enumerate("RGB")}
        chans.update(gt[cam])
        out[cam] = chans
    if timings is not None:
        timings["groundtruth"] = timings.get("groundtruth", 0.0) + t_gt
    return out
