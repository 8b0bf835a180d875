"""Self-checks of a rendered dataset (``omnisim check DIR``).

Every check prints its figure, its pass/fail threshold and the number of pixels it
used; ``omnisim check`` exits 1 if any fails. Pixel coordinates follow
:mod:`omniflow.conventions` (pixel centre of column j at x = j + 0.5); images are
sampled at continuous positions with ``cv2.remap`` (bilinear; index = coordinate - 0.5).

Checks (names as printed):

``eq1``
    every valid pixel's gt.r, gt.h satisfy eq. (1) for its own camera: the image
    radius v (h - tip_h) / (d + r) equals the pixel centre's radius h_i. Figure: max
    |difference| in pixels over all frames and cameras. For a unit with rig errors
    (``rig.errors`` in dataset.json, ``docs/decisions/rig_errors.md``) the traced
    model replaces eq. (1): the point (gt.r, gt.theta, gt.h) is projected through the
    actual geometry and its image radius compared with h_i.
``theta``
    gt.theta equals the pixel centre's polar angle (max |wrapped difference| x h_i, px);
    with rig errors, the polar angle of the point's traced projection.
``world``
    gt.X, gt.Y, gt.Z are the point (gt.r, gt.theta, gt.h) moved by the robot's pose of
    the frame (dataset.json robot.poses): max distance in metres.
``stereo``
    where gt.stereo.valid, gt.stereo.h_other equals eq. (3)/(4) of the other camera
    at (gt.r, gt.h) (with rig errors: the image radius of the point's traced
    projection into the other camera): max |difference|, px.
``flow_polar``
    gt.flow.dh, gt.flow.hdtheta agree with gt.flow.dx, dy (conventions.py): max px
    (format version 2: the same for gt.bflow).
``flo_file``
    the .flo files hold gt.flow.dx, dy where the flow is known (version 1: where
    gt.flow.valid; version 2: where the next position is defined, gt.flow.valid +
    occluded + outside) and the unknown value elsewhere: max |difference|, px, and no
    validity disagreement; version 2's mask PNGs must equal gt.flow.occluded, outside.
``files``
    every camera image (``camK.png``), mask PNG and ``.flo`` file of the checked
    frames decodes, has the image size and bit depth, and (``.flo``) holds only finite
    values (:mod:`omnisim.check_files`). Figure: files that do not (threshold 0); the
    detail names them. A broken ``.flo`` or mask is left out of ``flo_file``.
``flow_masks``
    format version 2: gt.flow.valid, .occluded, .outside (and the gt.bflow ones) are
    0/1, disjoint and 0 where gt.valid is 0; frame 0's backward flow is all 0. Figure:
    pixels that break this (threshold 0).
``static_world``
    on static objects (same pose in frames t and t+1), away from object boundaries
    (object-id mask eroded by one pixel in both frames), the world point at pixel p in
    frame t equals frame t+1's world point interpolated at p + gt.flow. Figure: 95th
    percentile of the distance divided by the local pixel footprint (the distance
    between neighbouring pixels' world points), i.e. in pixels of flow error.
``photometric``
    on Lambertian (diffuse) surfaces with valid flow, away from object boundaries,
    frame t+1's luminance sampled at p + gt.flow (bicubic) reproduces frame t much
    better than frame t+1 unwarped: figure = RMS residual with gt.flow / RMS residual
    with zero flow, over the same pixels. Catches a flow that does not move the image
    (zero, or far too small). Skipped when neither the robot nor any object moves
    between the frames (dataset.json poses), or when the frames differ by little more
    than their noise (unwarped residual < ``Tolerances.photometric_visible`` x
    sqrt(2) sigma): they then cannot tell a flow from zero flow.
``photometric_min``
    gt.flow is the photometric minimum among its neighbours: the mean squared residual
    with gt.flow divided by the smallest of those with gt.flow scaled by 1 -/+ 10 % and
    shifted by -/+ 0.1 px in x and in y. Fails when the figure is > 1 and the excess
    is significant (mean per-pixel excess > ``Tolerances.photometric_min_z`` standard
    errors). Catches a flow that is slightly wrong (scaled by 0.9, shifted by 0.3 px).
    Skipped (nothing to compare) when gt.flow and its best neighbour both reproduce frame
    t exactly (identical frames and zero flow); fails when a neighbour reproduces it
    exactly and gt.flow does not.
    Also printed: the residual over the render noise expected in a difference of two
    frames, sqrt(2) x sigma (Immerkaer's Laplacian estimator on the same surfaces; it
    also counts fine texture, so it errs high).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from omniflow.io.dataset import MASK_FILES, Dataset, DatasetError
from omnisim.check_files import dataset_file_problems
from omnisim.check_pixels import (
    image_polar,
    interior,
    is_lambertian,
    luma,
    mask_consistency,
    noise_sigma,
    remap,
    wrap,
)

__all__ = ["CheckResult", "Tolerances", "format_results", "run_checks"]


@dataclass(frozen=True)
class Tolerances:
    """Pass/fail thresholds of the checks (defaults are what ``omnisim check`` uses)."""

    #: eq. (1) / (3)-(4) / theta / polar flow consistency, pixels. The ground truth is
    #: exact in float64 and stored in float32; 0.02 px is the renderer's geometric target.
    geometry_px: float = 0.02
    #: world point vs rig cylindrical coordinates and robot pose, metres.
    world_m: float = 1e-4
    #: .flo vs EXR flow channels, pixels.
    flo_px: float = 1e-6
    #: static world point consistency, 95th percentile, in pixels of flow error.
    static_p95_px: float = 0.1
    #: photometric residual with gt.flow / residual with zero flow (RMS); 1 for zero flow by
    #: construction. Measured with the true flow (tests/omnisim/test_check.py,
    #: docs/decisions/render.md):
    #: 0.16 on scenes/large_motion.toml at 128 px (direct
    #: 64 spp + oidn), 0.69 on scenes/default.toml at 256 px (path 8 spp + oidn, median
    #: flow 0.3 px), 0.75 on the synthetic 64 px dataset with 1 % noise.
    photometric_ratio: float = 0.9
    #: photometric_min: the scale step (relative) and shift step (px) of the neighbours.
    photometric_scale_step: float = 0.1
    photometric_shift_px: float = 0.1
    #: photometric_min: mean squared residual of gt.flow / the best neighbour's. The true
    #: flow is the minimum (<= 1 by definition). Measured: true flow 0.88 (large_motion,
    #: 128 px), 0.994 (default, 256 px, path 8 spp + oidn), 0.995 (synthetic, 1 % noise);
    #: flow x 0.9 gave 2.18 / 1.007, shifted 0.3 px 1.47 / 1.31, zero 1.02 / 1.24.
    photometric_min_ratio: float = 1.0
    #: photometric_min fails only when gt.flow is also significantly worse than that
    #: neighbour: its mean per-pixel excess above this many standard errors. Measured z
    #: on large_motion at 128 px (direct 64 spp + oidn): true flow -6.7, zero 4.5,
    #: x 0.9 7.9, + 0.3 px 17.5; default scene at 64 px, 2 spp (motion 0.075 px, the
    #: frames' difference all noise): ratio 1.014, not significant.
    photometric_min_z: float = 3.0
    #: photometric is skipped unless the unwarped residual is at least this many times
    #: the noise-only figure sqrt(2) sigma (Immerkaer's estimate, which also counts
    #: texture, so it errs towards skipping). Measured: 3.56 on large_motion at 128 px,
    #: 1.56 on the default scene at 256 px (path 8 spp + oidn), 1.13 on the synthetic
    #: 64 px 1 % noise dataset, about 1.0 on the default scene at 64 px, 2 spp.
    photometric_visible: float = 1.3
    #: fewest pixels a statistical check needs; below it the check is skipped.
    min_pixels: int = 50


@dataclass
class CheckResult:
    """One check's outcome."""

    name: str
    description: str
    figure: float
    threshold: float
    unit: str
    n: int
    passed: bool | None  # None: skipped
    detail: str = ""

    @property
    def status(self) -> str:
        return "SKIP" if self.passed is None else ("PASS" if self.passed else "FAIL")


@dataclass
class _Acc:
    """Accumulates a residual over frames: max, and a bounded sample for percentiles."""

    max: float = 0.0
    n: int = 0
    sums: dict[str, float] = field(default_factory=dict)
    samples: list[NDArray] = field(default_factory=list)
    bad: int = 0

    def add(self, values: NDArray, keep: int = 0) -> None:
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.size == 0:
            return
        finite = np.isfinite(values)
        self.bad += int((~finite).sum())
        self.max = max(self.max, float(np.max(np.where(finite, values, np.inf))))
        self.n += values.size
        if keep:
            step = max(1, values.size // keep)
            self.samples.append(values[::step].astype(np.float32))

    def add_sum(self, key: str, value: float) -> None:
        self.sums[key] = self.sums.get(key, 0.0) + float(value)

    def percentile(self, q: float) -> float:
        if not self.samples:
            return math.nan
        v = np.concatenate(self.samples)
        v = np.where(np.isfinite(v), v, np.inf)
        return float(np.percentile(v, q))


#: Broken files the ``files`` check names in its detail (the count says how many in all).
_FILES_SHOWN = 5


def _files_result(broken: dict, n: int) -> CheckResult:
    """The ``files`` check: every camera PNG, mask PNG and .flo decodes (check_files.py)."""
    shown = "; ".join(f"{p}: {why}" for p, why in list(broken.items())[:_FILES_SHOWN])
    more = f"; and {len(broken) - _FILES_SHOWN} more" if len(broken) > _FILES_SHOWN else ""
    return CheckResult(
        "files",
        "camera PNGs, mask PNGs, .flo files decode at the image size (.flo finite)",
        float(len(broken)),
        0.0,
        "files",
        n,
        not broken,
        shown + more,
    )


@dataclass
class _Tally:
    """What the checks add up over the frames: the geometric accumulators, the
    photometric sums and the counts of the file and id checks."""

    acc: dict[str, _Acc] = field(
        default_factory=lambda: {
            name: _Acc()
            for name in (
                "eq1",
                "theta",
                "world",
                "stereo",
                "flow_polar",
                "flo_file",
                "static_world",
            )
        }
    )
    photo: _Acc = field(default_factory=_Acc)
    unknown_ids: set[int] = field(default_factory=set)
    flo_mismatch: int = 0
    n_valid: int = 0
    mask_bad: int = 0  # version 2: flow mask consistency
    mask_n: int = 0


@dataclass(frozen=True)
class _Scene:
    """The dataset's poses and objects, as the checks read them."""

    poses_robot: NDArray
    obj_meta: dict[int, dict]
    known_ids: set[int]
    lambertian_ids: list[int]

    @classmethod
    def of(cls, ds: Dataset) -> _Scene:
        obj_meta = {int(o["id"]): o for o in ds.meta.get("objects", [])}
        return cls(
            poses_robot=np.asarray(ds.meta["robot"]["poses"], dtype=np.float64),
            obj_meta=obj_meta,
            known_ids=set(obj_meta) | {0},
            lambertian_ids=[i for i, o in obj_meta.items() if is_lambertian(o.get("material"))],
        )


class _FrameCache:
    """``ds.read_frame`` keeping frames k - 1 and later (the temporal checks read k + 1)."""

    def __init__(self, ds: Dataset) -> None:
        self.ds = ds
        self.cache: dict[tuple[int, str], dict[str, NDArray]] = {}

    def __call__(self, k: int, cam: str) -> dict[str, NDArray]:
        key = (k, cam)
        if key not in self.cache:
            for old in [x for x in self.cache if x[0] < k - 1]:
                del self.cache[old]
            self.cache[key] = self.ds.read_frame(k, cam)
        return self.cache[key]


@dataclass(frozen=True)
class _Pixels:
    """One frame's pixel grid and the truth the temporal checks reuse."""

    x: NDArray
    y: NDArray
    world: NDArray
    fv: NDArray
    dx: NDArray
    dy: NDArray


def run_checks(
    ds: Dataset,
    *,
    frames: Iterable[int] | None = None,
    tol: Tolerances = Tolerances(),
    progress: bool = False,
) -> list[CheckResult]:
    """Run every check on the (rendered) frames ``frames`` (default: all done frames)."""
    done = ds.frames_done()
    if not done:
        raise DatasetError(f"{ds.dir}: no rendered frame to check")
    frames = sorted(set(done if frames is None else frames) & set(done))
    scene = _Scene.of(ds)
    tally = _Tally()
    # camera PNGs, mask PNGs and .flo files that do not decode (the ``files`` check)
    broken, n_files = dataset_file_problems(ds, frames)
    load = _FrameCache(ds)

    it: Iterable[int] = frames
    if progress:
        from tqdm import tqdm

        it = tqdm(frames, unit="frame", desc="omnisim check")

    for k in it:
        for cam in ds.cameras:
            ch = load(k, cam)
            pix = _check_frame(ds, k, cam, ch, scene, tally, broken)
            if k + 1 in frames:  # temporal checks need frame k + 1
                _check_pair(ds, k, cam, ch, load(k + 1, cam), pix, scene, tally, tol)

    results = _geometry_results(ds, tally, tol)
    results += _file_results(tally, tol, broken, n_files)
    results.append(_static_world_result(tally.acc["static_world"], tol))
    results += _photometric_results(tally.photo, tol)
    return results


def _check_frame(ds: Dataset, k: int, cam: str, ch: dict[str, NDArray], scene: _Scene,
                 tally: _Tally, broken: dict) -> _Pixels:  # fmt: skip
    """The checks of one frame of one camera: eq. (1), theta, the world point, stereo,
    the polar flow, the masks and the .flo file."""
    acc = tally.acc
    T = scene.poses_robot[k]
    unit = ds.unit(cam)
    other = ds.unit("cam2" if cam == "cam1" else "cam1")
    valid = ch["gt.valid"] > 0.5
    tally.n_valid += int(valid.sum())
    x, y = unit.pixel_centres()
    h_i, th_i = unit.polar_of_pixel(x, y)
    r = ch["gt.r"].astype(np.float64)
    h = ch["gt.h"].astype(np.float64)
    th = ch["gt.theta"].astype(np.float64)
    ids = np.unique(ch["gt.object"][valid]).astype(int)
    tally.unknown_ids |= set(ids.tolist()) - scene.known_ids

    # eq. (1) and theta (the traced model for a unit with rig errors)
    h_gt, th_gt = image_polar(unit, r, th, h, valid)
    acc["eq1"].add(np.abs(h_gt - h_i)[valid], keep=20000)
    acc["theta"].add((np.abs(wrap(th_gt - th_i)) * h_i)[valid])

    # world point vs rig cylindrical coordinates and the robot's pose
    p_rig = np.stack([r * np.cos(th), r * np.sin(th), h, np.ones_like(r)], axis=-1)
    p_w = p_rig @ T.T
    world = np.stack([ch["gt.X"], ch["gt.Y"], ch["gt.Z"]], axis=-1).astype(np.float64)
    acc["world"].add(np.linalg.norm(p_w[..., :3] - world, axis=-1)[valid])

    # stereo, eq. (3)/(4)
    sv = (ch["gt.stereo.valid"] > 0.5) & valid
    h_o = image_polar(other, r, th, h, sv)[0]
    acc["stereo"].add(np.abs(h_o - ch["gt.stereo.h_other"])[sv])

    # polar flow vs Cartesian flow
    fv = (ch["gt.flow.valid"] > 0.5) & valid
    dx = ch["gt.flow.dx"].astype(np.float64)
    dy = ch["gt.flow.dy"].astype(np.float64)
    h2, th2 = unit.polar_of_pixel(x + dx, y + dy)
    e_dh = np.abs((h2 - h_i) - ch["gt.flow.dh"])
    e_ht = np.abs(h_i * wrap(th2 - th_i) - ch["gt.flow.hdtheta"])
    acc["flow_polar"].add(np.maximum(e_dh, e_ht)[fv])
    if ds.version >= 2:  # the backward flow, wherever it is seen at t - 1
        bv = (ch["gt.bflow.valid"] > 0.5) & valid
        h2, th2 = unit.polar_of_pixel(x + ch["gt.bflow.dx"], y + ch["gt.bflow.dy"])
        e_dh = np.abs((h2 - h_i) - ch["gt.bflow.dh"])
        e_ht = np.abs(h_i * wrap(th2 - th_i) - ch["gt.bflow.hdtheta"])
        acc["flow_polar"].add(np.maximum(e_dh, e_ht)[bv])

    if ds.version >= 2:
        bad, n = mask_consistency(ch, k)
        tally.mask_bad += bad
        tally.mask_n += n
    # the .flo file and the mask PNGs, unless the files check found them broken
    masks = MASK_FILES if ds.version >= 2 else ()
    if not any(ds.path(k, cam, x) in broken for x in ("flo", *masks)):
        flow, flo_ok = ds.read_flo(k, cam)
        known = ds.flo_known(ch)  # version 1: gt.flow.valid; 2: every defined flow
        tally.flo_mismatch += int((flo_ok != known).sum())
        for name, mask in ds.read_flow_masks(k, cam).items():  # version 2's PNGs
            tally.flo_mismatch += int((mask != (ch[name] > 0.5)).sum())
        both = flo_ok & known
        e = np.maximum(np.abs(flow[..., 0] - ch["gt.flow.dx"]), np.abs(flow[..., 1] - dy))
        acc["flo_file"].add(e[both])
    return _Pixels(x=x, y=y, world=world, fv=fv, dx=dx, dy=dy)


def _check_pair(ds: Dataset, k: int, cam: str, ch: dict[str, NDArray], nxt: dict[str, NDArray],
                pix: _Pixels, scene: _Scene, tally: _Tally, tol: Tolerances) -> None:  # fmt: skip
    """The temporal checks of frames k and k + 1 of one camera: the static world point
    and the photometric residual."""
    unit = ds.unit(cam)
    x, y, fv, dx, dy = pix.x, pix.y, pix.fv, pix.dx, pix.dy
    int_t = interior(ch)
    int_n = interior(nxt)
    # cv2 index coordinates of the target: continuous (x + dx) - 0.5
    mx = x + np.where(fv, dx, 0.0) - 0.5
    my = y + np.where(fv, dy, 0.0) - 0.5
    jn = np.rint(mx).astype(np.int64)
    in_n = np.rint(my).astype(np.int64)
    inside = (jn >= 0) & (jn < unit.width) & (in_n >= 0) & (in_n < unit.height)
    jn_c = np.clip(jn, 0, unit.width - 1)
    in_c = np.clip(in_n, 0, unit.height - 1)
    same = nxt["gt.object"][in_c, jn_c] == ch["gt.object"]
    usable = fv & int_t & inside & int_n[in_c, jn_c] & same

    # static world point
    static_ids = [
        i
        for i, o in scene.obj_meta.items()
        if np.allclose(o["poses"][k], o["poses"][k + 1], rtol=0, atol=1e-12)
    ]
    st = usable & np.isin(ch["gt.object"], static_ids)
    if st.any():
        world = pix.world
        wn = np.stack([remap(nxt[c], mx, my) for c in ("gt.X", "gt.Y", "gt.Z")], -1)
        dist = np.linalg.norm(wn.astype(np.float64) - world, axis=-1)
        # local pixel footprint: distance between horizontally/vertically adjacent
        # pixels' world points in frame t (the larger of the two, inside the object)
        fx = np.zeros_like(dist)
        fy = np.zeros_like(dist)
        fx[:, :-1] = np.linalg.norm(world[:, 1:] - world[:, :-1], axis=-1)
        fy[:-1, :] = np.linalg.norm(world[1:, :] - world[:-1, :], axis=-1)
        foot = np.maximum(fx, fy)
        ok = st & (foot > 0)
        tally.acc["static_world"].add((dist / np.where(foot > 0, foot, 1.0))[ok], keep=20000)

    # photometric: gt.flow against zero flow and against its neighbours
    lam = usable & np.isin(ch["gt.object"], scene.lambertian_ids)
    if lam.sum() >= tol.min_pixels:
        moves = not np.allclose(scene.poses_robot[k], scene.poses_robot[k + 1], rtol=0,
                                atol=1e-12)  # fmt: skip
        moves |= len(static_ids) < len(scene.obj_meta)
        _add_photometric(tally.photo, ch, nxt, pix, lam, int_n, scene, tol, moves)


def _add_photometric(photo: _Acc, ch: dict[str, NDArray], nxt: dict[str, NDArray], pix: _Pixels,
                     lam: NDArray, int_n: NDArray, scene: _Scene, tol: Tolerances,
                     moves: bool) -> None:  # fmt: skip
    """Add one frame pair's photometric sums: the residual of frame t + 1 warped by
    gt.flow, by zero flow and by gt.flow's neighbours (scaled, shifted), on the
    Lambertian pixels ``lam``."""
    x, y = pix.x, pix.y
    i_t = luma(ch)
    i_n = luma(nxt).astype(np.float32)
    fx, fy = np.where(pix.fv, pix.dx, 0.0), np.where(pix.fv, pix.dy, 0.0)
    a, e = tol.photometric_scale_step, tol.photometric_shift_px
    trials = {
        "flow": (1.0, 0.0, 0.0),
        "zero": (0.0, 0.0, 0.0),
        f"x{1 - a:g}": (1 - a, 0.0, 0.0),
        f"x{1 + a:g}": (1 + a, 0.0, 0.0),
        f"dx-{e:g}": (1.0, -e, 0.0),
        f"dx+{e:g}": (1.0, e, 0.0),
        f"dy-{e:g}": (1.0, 0.0, -e),
        f"dy+{e:g}": (1.0, 0.0, e),
    }
    sq_flow = None
    for name, (sc, ox, oy) in trials.items():
        warped = remap(i_n, x + sc * fx + ox - 0.5, y + sc * fy + oy - 0.5, True)
        sq = (i_t - warped.astype(np.float64))[lam] ** 2
        photo.add_sum(name, float(np.sum(sq)))
        if sq_flow is None:
            sq_flow = sq
        elif name != "zero":
            # per-pixel excess of gt.flow over this neighbour, for its standard error
            photo.add_sum("d2:" + name, float(np.sum((sq_flow - sq) ** 2)))
    s_t, n_t = noise_sigma(i_t, lam)
    s_n, n_n = noise_sigma(i_n, int_n & np.isin(nxt["gt.object"], scene.lambertian_ids))
    if n_t and n_n:
        photo.add_sum("sig2", (s_t**2 + s_n**2) / 2.0)
        photo.add_sum("pairs", 1)
    photo.add_sum("n", int(lam.sum()))
    photo.add_sum("moving_pairs", int(moves))
    photo.add_sum("mean", float(np.sum(i_t[lam])))
    photo.add(np.hypot(fx, fy)[lam], keep=20000)


def _geometry_results(ds: Dataset, tally: _Tally, tol: Tolerances) -> list[CheckResult]:
    """The geometric checks' results: eq. (1), theta, world, stereo, polar flow."""
    results: list[CheckResult] = []
    acc = tally.acc
    # with rig errors the geometric checks use the traced model: say so
    traced = any(getattr(ds.unit(c), "errors", None) is not None for c in ds.cameras)
    via = " (traced model: rig errors)" if traced else ""

    def geom(name: str, desc: str, a: _Acc, thr: float, unit: str) -> None:
        passed = a.n > 0 and a.bad == 0 and a.max <= thr
        detail = f"{a.bad} non-finite" if a.bad else ""
        if name == "eq1" and a.n:
            detail = f"p99 {a.percentile(99):.3g} {unit}"
        results.append(
            CheckResult(
                name,
                desc,
                a.max if a.n else math.nan,
                thr,
                unit,
                a.n,
                passed if a.n or name == "eq1" else None,
                detail,
            )
        )

    geom(
        "eq1",
        "gt.r, gt.h vs eq. (1) at the pixel centre (max)" + via,
        acc["eq1"],
        tol.geometry_px,
        "px",
    )
    geom(
        "theta",
        "gt.theta vs the pixel centre's angle, x h_i (max)" + via,
        acc["theta"],
        tol.geometry_px,
        "px",
    )
    geom(
        "world",
        "gt.X, Y, Z vs (gt.r, theta, h) and the robot pose (max)",
        acc["world"],
        tol.world_m,
        "m",
    )
    geom(
        "stereo",
        "gt.stereo.h_other vs eq. (3)/(4) (max)" + via,
        acc["stereo"],
        tol.geometry_px,
        "px",
    )
    geom(
        "flow_polar",
        "gt.flow.dh, hdtheta vs gt.flow.dx, dy (max)",
        acc["flow_polar"],
        tol.geometry_px,
        "px",
    )
    return results


def _file_results(tally: _Tally, tol: Tolerances, broken: dict, n_files: int) -> list[CheckResult]:
    """The results of the masks, the .flo files, the files' decoding and the object ids."""
    results: list[CheckResult] = []
    results.append(
        CheckResult(
            "flow_masks",
            "gt.flow/bflow valid, occluded, outside: 0/1, disjoint, inside gt.valid",
            float(tally.mask_bad) if tally.mask_n else math.nan,
            0.0,
            "px",
            tally.mask_n,
            (tally.mask_bad == 0) if tally.mask_n else None,
            "" if tally.mask_n else "format version 1: no masks",
        )
    )
    r_flo = tally.acc["flo_file"]
    results.append(
        CheckResult(
            "flo_file",
            ".flo vs gt.flow.dx, dy (max; validity must agree)",
            r_flo.max if r_flo.n else math.nan,
            tol.flo_px,
            "px",
            r_flo.n,
            (tally.flo_mismatch == 0 and r_flo.max <= tol.flo_px)
            if (r_flo.n or tally.flo_mismatch)
            else None,
            f"{tally.flo_mismatch} validity disagreements",
        )
    )
    results.append(_files_result(broken, n_files))
    if tally.unknown_ids:
        results.append(
            CheckResult(
                "object_ids",
                "gt.object ids listed in dataset.json objects",
                len(tally.unknown_ids),
                0,
                "unknown ids",
                tally.n_valid,
                False,
                f"unknown: {sorted(tally.unknown_ids)}",
            )
        )

    return results


def _static_world_result(sw: _Acc, tol: Tolerances) -> CheckResult:
    """The static world point's result (p95 of its offset, in pixel footprints)."""
    if sw.n >= tol.min_pixels:
        p95 = sw.percentile(95)
        return CheckResult(
            "static_world",
            "world point at p (t) vs at p + flow (t+1), static objects (p95)",
            p95,
            tol.static_p95_px,
            "px",
            sw.n,
            bool(p95 <= tol.static_p95_px),
            f"median {sw.percentile(50):.3g} px, max {sw.max:.3g} px",
        )
    else:
        return CheckResult(
            "static_world",
            "world point at p (t) vs at p + flow (t+1), static objects (p95)",
            math.nan,
            tol.static_p95_px,
            "px",
            sw.n,
            None,
            "needs two consecutive frames with static, flow-valid interior pixels",
        )


def _photometric_results(photo: _Acc, tol: Tolerances) -> list[CheckResult]:
    """The photometric checks' results: gt.flow's residual against zero flow's
    (``photometric``) and against its best neighbour's (``photometric_min``)."""
    results: list[CheckResult] = []
    s = photo.sums
    name0 = "warp(frame t+1, gt.flow) vs frame t on Lambertian surfaces"
    if s.get("n", 0) >= tol.min_pixels:
        n = s["n"]
        rms = math.sqrt(s["flow"] / n)
        rms0 = math.sqrt(s["zero"] / n)
        mean = s["mean"] / n
        median_flow = photo.percentile(50)
        ratio = rms / rms0 if rms0 > 0 else (0.0 if rms == 0 else math.inf)
        sigma = math.sqrt(s["sig2"] / s["pairs"]) if s.get("pairs") else math.nan
        # the frames differ visibly more than their noise (else they cannot tell a flow
        # from zero flow): unwarped residual over sqrt(2) x Immerkaer's sigma
        visible = rms0 / (math.sqrt(2) * sigma) if sigma > 0 else math.inf
        moving = s.get("moving_pairs", 0) > 0 and visible >= tol.photometric_visible
        results.append(
            CheckResult(
                "photometric",
                name0 + " (RMS residual / that with zero flow)",
                ratio,
                tol.photometric_ratio,
                "",
                int(n),
                bool(ratio <= tol.photometric_ratio) if moving else None,
                f"residual RMS {rms:.4g} = {rms / mean:.2%} of the mean {mean:.4g}, with zero "
                f"flow {rms0:.4g}; median |flow| {median_flow:.3g} px"
                + f"; zero-flow residual / (sqrt(2) sigma_noise) {visible:.3g}"
                + (
                    ""
                    if moving
                    else f" (< {tol.photometric_visible:g} or nothing moves: skipped, the "
                    "frames cannot tell a flow from zero flow)"
                ),
            )
        )
        neighbours = {k: v for k, v in s.items() if k[:1] in ("x", "d") and ":" not in k}
        best = min(neighbours, key=neighbours.get)
        # Nothing to compare when gt.flow and its best neighbour both reproduce frame t
        # exactly (identical frames and zero flow, which scaled by 1 -/+ 10 % is itself):
        # skipped. A neighbour that does while gt.flow does not: gt.flow is worse.
        exact = neighbours[best] == 0
        untestable = exact and s["flow"] == 0
        fig = math.nan if untestable else (math.inf if exact else s["flow"] / neighbours[best])
        # is gt.flow significantly worse than its best neighbour? The mean per-pixel excess
        # against its standard error, with n / 9 independent pixels (the bicubic warp and
        # the denoiser correlate 3 x 3 neighbourhoods).
        excess = (s["flow"] - neighbours[best]) / n
        var = max(s["d2:" + best] / n - excess**2, 0.0)
        if var > 0:
            z = excess / math.sqrt(var / (n / 9.0))
        else:  # identical residuals (e.g. a static frame pair): no excess, or all of it
            z = math.copysign(math.inf, excess) if excess != 0 else 0.0
        worse = exact or (fig > tol.photometric_min_ratio and z > tol.photometric_min_z)
        detail = "; ".join(
            f"{k} {v / s['flow']:.4g}" if s["flow"] > 0 else f"{k} n/a"
            for k, v in neighbours.items()
        )
        if s.get("pairs") and sigma > 0:
            detail += f"; residual / (sqrt(2) sigma_noise) {rms / (math.sqrt(2) * sigma):.3g}"
        results.append(
            CheckResult(
                "photometric_min",
                "gt.flow's mean squared residual / its best neighbour's (flow scaled -/+ "
                f"{tol.photometric_scale_step:g}, shifted -/+ {tol.photometric_shift_px:g} px)",
                fig,
                tol.photometric_min_ratio,
                "",
                int(n),
                None if untestable else not worse,
                (
                    f"gt.flow and {best} both reproduce frame t exactly (residual 0): "
                    "nothing to compare, skipped; "
                    if untestable
                    else ""
                )
                + f"best neighbour {best} (excess z = {z:.3g}; fails when > "
                f"{tol.photometric_min_z:g}); neighbour / gt.flow: {detail}",
            )
        )
    else:
        for name in ("photometric", "photometric_min"):
            results.append(
                CheckResult(
                    name,
                    name0,
                    math.nan,
                    tol.photometric_ratio if name == "photometric" else tol.photometric_min_ratio,
                    "",
                    int(s.get("n", 0)),
                    None,
                    "needs two consecutive frames with Lambertian, flow-valid interior pixels",
                )
            )
    return results


def format_results(results: list[CheckResult]) -> str:
    """One line per check: name, status, figure vs threshold, pixels used, detail."""
    lines = []
    for r in results:
        fig = "n/a" if isinstance(r.figure, float) and math.isnan(r.figure) else f"{r.figure:.4g}"
        unit = f" {r.unit}" if r.unit else ""
        line = (
            f"{r.status}  {r.name:<12} {fig}{unit} (threshold <= {r.threshold:g}{unit}; "
            f"n = {r.n})  {r.description}"
        )
        if r.detail:
            line += f"  [{r.detail}]"
        lines.append(line)
    failed = [r.name for r in results if r.passed is False]
    lines.append("all checks passed" if not failed else f"FAILED: {', '.join(failed)}")
    return "\n".join(lines)
