"""Run omniflow's variants and the OpenCV baselines over a dataset and score them.

The harness reads the dataset only through :func:`omniflow.dataset.open_dataset`
(``dataset.json`` and the EXR channels), so any generator that writes that
contract is scored the same way.

Inputs. Every method sees the same frames: the Rec. 709 luminance of the
linear RGB, scaled once per dataset so that the 99.5th percentile of frame
0's valid pixels maps to 255, rounded to 8 bits. OpenCV takes these uint8
images; omniflow takes the same values as float32 / 255.

Units. omniflow estimates velocities per frame interval (pixels/frame,
radians/frame, metres/frame); the ground truth is the displacement of each
material point from frame t to t + 1 (pixels). Both are per frame and are
compared directly; for motions of a pixel or more the first-order velocity
and the finite displacement differ, which shows in the large-motion scenes.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
import warnings
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.conventions import LUMA_WEIGHTS
from omniflow.dataset import grey_of

from . import baselines as bl
from .metrics import flow_errors, flow_summary, stats, stereo_errors, stereo_summary
from .motion import point_motion, robot_motion
from .sampling import sample_truth

__all__ = [
    "VARIANT_CHOICES",
    "FramePair",
    "InputError",
    "Results",
    "TrueMatches",
    "omniflow_variants",
    "run_validation",
    "true_matches",
    "variant_name",
]

#: The selectable choices of OmniFlowConfig that each get a row, default first.
VARIANT_CHOICES: dict[str, tuple[str, ...]] = {
    "match_method": ("robust", "paper"),
    "gradients": ("first", "average"),
    "temporal": ("difference", "dct3d"),
    "solver": ("direct", "pooled"),
}
_SHORT = {
    "robust": "robust",
    "paper": "paper",
    "first": "grad1",
    "average": "gradavg",
    "difference": "diff",
    "dct3d": "dct3d",
    "direct": "direct",
    "pooled": "pooled",
}

FLOW_TRUTH = (
    "gt.valid",
    "gt.object",
    "gt.flow.valid",
    "gt.flow.dx",
    "gt.flow.dy",
    "gt.flow.dh",
    "gt.flow.hdtheta",
    "gt.r",
)
STEREO_TRUTH = (
    "gt.valid",
    "gt.object",
    "gt.stereo.valid",
    "gt.stereo.h_other",
    "gt.r",
    "gt.h",
    "gt.X",
    "gt.Y",
    "gt.Z",
)
CAMERAS = ("cam1", "cam2")
#: At most this many matched points (a fixed random subset) go into the odometry fit.
ODOMETRY_POINTS = 2000


@dataclass(frozen=True)
class TrueMatches:
    """A variant that skips matching: omniflow's flow step on the TRUE stereo matches.

    The points are the cam1 pixels whose radial gradient magnitude is in the
    top ``100 - percentile`` % (the paper's significant points, from the 8-bit
    frame by central differences) and that cam2 sees (``gt.stereo.valid``);
    their match is ``h2 = gt.stereo.h_other``. The row isolates the flow
    solution (section 5.3) from the matching (section 5.2).
    """

    config: Any
    percentile: float = 80.0

    def __getattr__(self, name: str) -> Any:  # temporal, gradients, ... of the inner config
        if name == "config":
            raise AttributeError(name)
        return getattr(self.config, name)


def variant_name(config: Any) -> str:
    """Row name of an OmniFlowConfig, e.g. ``omniflow[robust,grad1,diff,direct]``;
    ``omniflow[truth,...]`` for :class:`TrueMatches`. Other fields that differ from
    ``OmniFlowConfig()`` follow a semicolon: ``omniflow[paper,grad1,diff,direct;band=0.25]``."""
    inner = config.config if isinstance(config, TrueMatches) else config
    parts = [_SHORT.get(str(getattr(inner, k)), str(getattr(inner, k)))
             for k in VARIANT_CHOICES if hasattr(inner, k)]  # fmt: skip
    if isinstance(config, TrueMatches) and parts:
        parts[0] = "truth"
    extra = ""
    if dataclasses.is_dataclass(inner):
        try:
            base = type(inner)()
        except TypeError:
            base = None
        if base is not None:
            diffs = [f"{f.name}={getattr(inner, f.name)!r}".replace("'", "")
                     for f in dataclasses.fields(inner)
                     if f.name not in VARIANT_CHOICES
                     and getattr(inner, f.name) != getattr(base, f.name)]  # fmt: skip
            extra = ";" + ",".join(diffs) if diffs else ""
    return f"omniflow[{','.join(parts)}{extra}]"


def omniflow_variants(mode: str = "all", *, true_matches: bool = True) -> list[tuple[str, Any]]:
    """(name, OmniFlowConfig) for each variant, the default configuration first.

    ``mode``: ``"default"`` (only the default), ``"oat"`` (the default plus each
    choice changed one at a time, plus the paper's configuration), ``"all"``
    (every combination). With
    ``true_matches`` (not for "default") two more rows run the flow step of the
    default and of the paper's configuration on the true matches
    (:class:`TrueMatches`).
    """
    from omniflow.pipeline import OmniFlowConfig

    base = OmniFlowConfig()
    names = {f.name for f in dataclasses.fields(OmniFlowConfig)}
    choices = {k: v for k, v in VARIANT_CHOICES.items() if k in names}
    configs: list[Any] = [base]
    if mode == "oat":
        for key, values in choices.items():
            for val in values:
                if val != getattr(base, key):
                    configs.append(dataclasses.replace(base, **{key: val}))
    elif mode == "all":
        for combo in itertools.product(*choices.values()):
            cfg = dataclasses.replace(base, **dict(zip(choices, combo, strict=True)))
            if cfg != base:
                configs.append(cfg)
    elif mode != "default":
        raise InputError(f"variants = {mode!r}: expected 'default', 'oat' or 'all'")
    paper = OmniFlowConfig.paper() if hasattr(OmniFlowConfig, "paper") else base
    if mode != "default" and paper not in configs:  # the paper's exact configuration
        configs.append(paper)
    if true_matches and mode != "default":
        configs.append(TrueMatches(base))
        paper = OmniFlowConfig.paper() if hasattr(OmniFlowConfig, "paper") else base
        if paper != base:
            configs.append(TrueMatches(paper))
    return [(variant_name(c), c) for c in configs]


def true_matches(
    image: NDArray, truth: dict[str, NDArray], rig: Any, percentile: float = 80.0
) -> Any:
    """The true stereo matches at cam1's significant pixels (see :class:`TrueMatches`)."""
    from omniflow.matching import Matches

    unit = rig.cam1
    g = image.astype(np.float64)
    gy, gx = np.gradient(g)
    x, y = unit.pixel_centres()
    h1, theta = unit.polar_of_pixel(x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        f_h = np.abs((x - unit.x_c) * gx + (y - unit.y_c) * gy) / h1
    seen = (truth["gt.valid"] > 0.5) & (truth["gt.stereo.valid"] > 0.5) & (h1 >= 6.0)
    seen &= h1 <= unit.r_m - 4.0
    seen &= np.isfinite(truth["gt.stereo.h_other"]) & np.isfinite(f_h)
    if not seen.any():
        z = np.zeros(0)
        return Matches(x=z, y=z, theta=z, h1=z, h2=z, score=z, n_significant=0, method="truth")
    sig = seen & (f_h >= np.percentile(f_h[seen], percentile))
    ii, jj = np.nonzero(sig)
    return Matches(
        x=x[ii, jj],
        y=y[ii, jj],
        theta=theta[ii, jj],
        h1=h1[ii, jj],
        h2=truth["gt.stereo.h_other"][ii, jj].astype(np.float64),
        score=np.ones(ii.size),
        n_significant=int(ii.size),
        method="truth",
    )


class InputError(ValueError):
    """The dataset or the request cannot be scored (the message says why)."""


#: Columns the harness reads from OmniFlowResult.columns.
RESULT_COLUMNS = ("x", "y", "theta", "h1", "h2", "r", "h", "dh1_dt", "dtheta_dt", "dr_dt", "dx",
                  "dy", "x2", "y2", "dh2_dt", "dx2", "dy2")  # fmt: skip


class _FailedResult:
    """Stands in for the result of an estimate that raised: no points."""

    def __init__(self) -> None:
        self.columns = {k: np.zeros(0) for k in RESULT_COLUMNS}
        self.timings: dict[str, float] = {}
        self.n_significant = None


# -- results container ---------------------------------------------------------------


@dataclass
class MethodInfo:
    name: str
    kind: str  # "omniflow" | "baseline"
    config: dict[str, Any] = field(default_factory=dict)
    default: bool = False
    paper: bool = False  # OmniFlowConfig.paper(), on the method's own matches


@dataclass
class FramePair:
    """What the report draws: the inputs and outputs of the first scored pair."""

    t: int
    images: dict[str, NDArray]  # cam -> uint8 (H, W) at t
    truth: dict[str, dict[str, NDArray]]  # cam -> gt channels at t
    dense: dict[str, dict[str, NDArray]]  # baseline -> cam -> (H, W, 2)
    points: dict[str, dict[str, NDArray]]  # cam -> x, y, dx, dy, epe (default omniflow)
    panorama: NDArray | None = None  # uint8 panorama of cam1 at t


@dataclass
class Results:
    """Everything the report needs, filled by :func:`run_validation`."""

    dataset: dict[str, Any]
    methods: list[MethodInfo]
    rows: list[dict[str, Any]] = field(default_factory=list)
    #: (method, points, cam) -> list of per-frame flow error dicts (with "noc", "range")
    flow: dict[tuple[str, str, str], list[dict[str, NDArray]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    #: method -> list of per-frame stereo error dicts, and counts
    stereo: dict[str, list[dict[str, NDArray]]] = field(default_factory=lambda: defaultdict(list))
    stereo_counts: dict[str, dict[str, int]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(int))
    )
    #: method -> list of per-frame derived-quantity records
    derived: dict[str, list[dict[str, Any]]] = field(default_factory=lambda: defaultdict(list))
    #: method -> seconds per frame pair (both cameras)
    times: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    #: method -> per-stage seconds (omniflow), summed over pairs
    stages: dict[str, dict[str, float]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(float))
    )
    snapshot: FramePair | None = None
    notes: list[str] = field(default_factory=list)


# -- inputs ---------------------------------------------------------------------------


def _grey(chans: dict[str, NDArray]) -> NDArray:
    wr, wg, wb = LUMA_WEIGHTS
    return wr * chans["R"] + wg * chans["G"] + wb * chans["B"]


class _Frames:
    """8-bit grey frames of both cameras, read once and cached."""

    def __init__(self, ds: Any):
        self.ds = ds
        self.cache: dict[tuple[int, str], NDArray] = {}
        self.scale: float | None = None

    def _set_scale(self) -> None:
        vals = []
        for cam in CAMERAS:
            ch = self.ds.read_frame(0, cam)
            g = grey_of(ch)
            ok = (ch["gt.valid"] > 0.5) & np.isfinite(g)
            vals.append(g[ok] if ok.any() else g[np.isfinite(g)])
        v = np.concatenate(vals)
        top = float(np.percentile(v, 99.5)) if v.size else 0.0
        self.scale = 255.0 / top if top > 0 else 1.0

    def u8(self, k: int, cam: str, chans: dict[str, NDArray] | None = None) -> NDArray:
        key = (k, cam)
        if key not in self.cache:
            if self.scale is None:
                self._set_scale()
            g = grey_of(chans if chans is not None else self.ds.read_frame(k, cam))
            g = np.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
            self.cache[key] = np.clip(np.rint(g * self.scale), 0, 255).astype(np.uint8)
        return self.cache[key]

    def drop_before(self, k: int) -> None:
        for key in [key for key in self.cache if key[0] < k]:
            del self.cache[key]


def _window(t: int, count: int, need: int) -> tuple[int, int]:
    """First frame and length of a window of ``need`` frames that holds t and t + 1."""
    start = max(0, min(t, count - need))
    return start, min(need, count - start)


def _meta_poses(meta: dict[str, Any]) -> tuple[list | None, dict[int, list]]:
    robot = meta.get("robot", {}).get("poses") if isinstance(meta.get("robot"), dict) else None
    objects = {}
    for obj in meta.get("objects", []) or []:
        if isinstance(obj, dict) and "poses" in obj and "id" in obj:
            objects[int(obj["id"])] = obj["poses"]
    return robot, objects


# -- scoring helpers -------------------------------------------------------------------


def _score_flow(
    est: dict[str, NDArray], x: NDArray, y: NDArray, truth: dict[str, NDArray]
) -> dict[str, NDArray]:
    tr = sample_truth(truth, x, y, channels=FLOW_TRUTH)
    has = tr["bilinear_ok"] & (tr["gt.valid"] > 0.5)
    for k in ("dx", "dy", "dh", "hdtheta"):
        has &= np.isfinite(est[k])
    err = flow_errors(
        {k: np.asarray(est[k])[has] for k in ("dx", "dy", "dh", "hdtheta")},
        {k: tr[f"gt.flow.{k}"][has] for k in ("dx", "dy", "dh", "hdtheta")},
    )
    err["noc"] = tr["gt.flow.valid"][has] > 0.5
    err["range"] = tr["gt.r"][has]
    err["object"] = tr["gt.object"][has]
    err["n_points"] = np.asarray(x).size
    return err


def _score_dense(
    flow_at: Callable[..., dict[str, NDArray]], truth: dict[str, NDArray], dense: NDArray | None
) -> dict[str, NDArray]:
    """Score a dense field at every pixel centre that sees the scene."""
    valid = truth["gt.valid"] > 0.5
    ii, jj = np.nonzero(valid)
    x, y = jj + 0.5, ii + 0.5
    if dense is not None:
        est = {"dx": dense[ii, jj, 0].astype(np.float64), "dy": dense[ii, jj, 1].astype(np.float64)}
        from .metrics import polar_components

        unit_c = truth["_centre"]
        est["dh"], est["hdtheta"] = polar_components(x, y, est["dx"], est["dy"], *unit_c)
    else:
        est = flow_at(x, y)
    gt = {
        k: truth[f"gt.flow.{k}"][ii, jj].astype(np.float64) for k in ("dx", "dy", "dh", "hdtheta")
    }
    has = np.all([np.isfinite(v) for v in (*est.values(), *gt.values())], axis=0)
    err = flow_errors({k: v[has] for k, v in est.items()}, {k: v[has] for k, v in gt.items()})
    err["noc"] = truth["gt.flow.valid"][ii, jj][has] > 0.5
    err["range"] = truth["gt.r"][ii, jj][has].astype(np.float64)
    err["object"] = truth["gt.object"][ii, jj][has].astype(np.float64)
    err["n_points"] = x.size
    return err


def _omniflow_points(cols: dict[str, NDArray], cam: str) -> tuple[NDArray, NDArray, dict]:
    """Points and flow of one camera from OmniFlowResult.columns."""
    if cam == "cam1":
        x, y, h = cols["x"], cols["y"], cols["h1"]
        est = {
            "dx": cols["dx"],
            "dy": cols["dy"],
            "dh": cols["dh1_dt"],
            "hdtheta": h * cols["dtheta_dt"],
        }
    else:
        x, y, h = cols["x2"], cols["y2"], cols["h2"]
        est = {
            "dx": cols["dx2"],
            "dy": cols["dy2"],
            "dh": cols["dh2_dt"],
            "hdtheta": h * cols["dtheta_dt"],
        }
    return (
        np.asarray(x, np.float64),
        np.asarray(y, np.float64),
        {k: np.asarray(v, np.float64) for k, v in est.items()},
    )


def _significant(result: Any) -> tuple[NDArray, NDArray] | int | None:
    """The significant points (x, y) of cam1 that matching started from, if exposed."""
    for name in ("significant", "significant_points"):
        sig = getattr(result, name, None)
        if sig is not None:
            if isinstance(sig, dict):
                return np.asarray(sig["x"]), np.asarray(sig["y"])
            if isinstance(sig, tuple | list) and len(sig) == 2:
                return np.asarray(sig[0]), np.asarray(sig[1])
    for source in (
        getattr(result, "stats", None),
        getattr(result, "counts", None),
        getattr(result, "info", None),
    ):
        if isinstance(source, dict):
            for key in ("n_significant", "significant"):
                if key in source and np.isscalar(source[key]):
                    return int(source[key])
    n = getattr(result, "n_significant", None)
    return int(n) if n is not None else None


# -- the run ----------------------------------------------------------------------------


def run_validation(
    dataset_dir: str | Path,
    *,
    variants: str | Sequence[tuple[str, Any]] = "all",
    baselines: Iterable[str] = bl.BASELINES,
    frames: Sequence[int] | None = None,
    progress: bool = True,
    estimate: Callable[..., Any] | None = None,
) -> Results:
    """Score every omniflow variant and baseline on every frame pair of a dataset.

    Parameters
    ----------
    dataset_dir : path
        An omnisim dataset directory (``dataset.json`` + ``frames/``).
    variants : "all" | "oat" | "default" | list of (name, OmniFlowConfig)
        Which omniflow configurations get a row (:func:`omniflow_variants`).
    baselines : iterable of str
        Names from :data:`validation.baselines.BASELINES`.
    frames : sequence of int, optional
        The frames t to score (pair t -> t + 1); default every complete pair.
    progress : bool
        Show a tqdm progress bar (on stderr).
    estimate : callable, optional
        Stand-in for :func:`omniflow.pipeline.estimate` with the same signature
        and result (tests use an oracle built from the truth).
    """
    from tqdm import tqdm

    from omniflow.dataset import open_dataset

    if estimate is None:
        from omniflow.pipeline import estimate

    ds = open_dataset(dataset_dir)
    rig = ds.rig
    done = set(ds.frames_done())
    pairs = [t for t in range(ds.frame_count - 1) if t in done and t + 1 in done]
    if frames is not None:
        wanted = sorted(set(int(t) for t in frames))
        missing = [t for t in wanted if t not in pairs]
        if missing:
            raise InputError(f"{dataset_dir}: no complete frame pair t -> t + 1 for t = {missing}")
        pairs = wanted
    if not pairs:
        raise InputError(f"{dataset_dir}: no complete frame pair (needs two consecutive frames)")
    vlist = omniflow_variants(variants) if isinstance(variants, str) else list(variants)
    baselines = list(baselines)
    for b in baselines:
        if b not in bl.BASELINES:
            raise InputError(f"unknown baseline {b!r}; expected some of {bl.BASELINES}")

    meta = ds.meta
    scene = meta.get("scene", {}) if isinstance(meta.get("scene"), dict) else {}
    results = Results(
        dataset={
            "path": str(Path(dataset_dir).resolve()),
            "scene": scene.get("name", Path(dataset_dir).name),
            "frames": ds.frame_count,
            "pairs": pairs,
            "frame_interval_s": ds.frame_interval,
            "size": [rig.cam1.width, rig.cam1.height],
            "rig": {"d": rig.d, "R": rig.R, "s": rig.s},
            "render": meta.get("render", {}),
            "objects": {str(k): v for k, v in ds.objects.items()},
        },
        methods=[
            MethodInfo(name, "omniflow", _config_dict(cfg), i == 0, _is_paper_config(cfg))
            for i, (name, cfg) in enumerate(vlist)
        ]
        + [MethodInfo(b, "baseline") for b in baselines],
    )
    default_name = vlist[0][0] if vlist else None
    robot_poses, object_poses = _meta_poses(meta)
    frames_src = _Frames(ds)
    need = 3 if any(getattr(c, "temporal", "") == "dct3d" for _, c in vlist) else 2
    need = min(need, len(done))
    units = {"cam1": rig.cam1, "cam2": rig.cam2}

    steps = len(pairs) * (len(vlist) + len(baselines))
    bar = tqdm(
        total=steps,
        desc=f"omnivalidate {results.dataset['scene']}",
        unit="run",
        disable=not progress,
        leave=False,
    )
    try:
        for t in pairs:
            truth = {cam: ds.read_frame(t, cam) for cam in CAMERAS}
            for cam in CAMERAS:
                truth[cam]["_centre"] = (units[cam].x_c, units[cam].y_c)  # type: ignore[assignment]
            start, length = _window(t, ds.frame_count, need)
            window = list(range(start, start + length))
            if not all(k in done for k in window):
                window = [t, t + 1]
                start = t
            u8 = {
                cam: [frames_src.u8(k, cam, truth[cam] if k == t else None) for k in window]
                for cam in CAMERAS
            }
            frames_src.drop_before(start)
            grey = {cam: [f.astype(np.float32) / 255.0 for f in u8[cam]] for cam in CAMERAS}
            first = {cam: u8[cam][t - start] for cam in CAMERAS}
            second = {cam: u8[cam][t + 1 - start] for cam in CAMERAS}

            # Baselines first: their dense fields are also sampled at every variant's points.
            dense: dict[str, dict[str, Any]] = {}
            for b in baselines:
                bar.set_postfix_str(f"t={t} {b}")
                fields = {
                    cam: bl.dense_baseline(b, first[cam], second[cam], units[cam])
                    for cam in CAMERAS
                }
                dense[b] = fields
                results.times[b].append(sum(f.seconds for f in fields.values()))
                for cam in CAMERAS:
                    f = fields[cam]
                    flow = f.flow if isinstance(f, bl.DenseFlow) else None
                    err = _score_dense(f.at, truth[cam], flow)
                    results.flow[(b, "dense", cam)].append(err)
                    results.rows.append(_flow_row(t, b, "dense", cam, err, f.seconds))
                bar.update(1)

            default_pts: dict[str, tuple[NDArray, NDArray]] = {}
            snap_points: dict[str, dict[str, NDArray]] = {}
            for vi, (name, cfg) in enumerate(vlist):
                bar.set_postfix_str(f"t={t} {name}")
                g1 = grey["cam1"]
                g2 = grey["cam2"]
                if getattr(cfg, "temporal", "") != "dct3d":
                    g1, g2 = g1[t - start : t - start + 2], g2[t - start : t - start + 2]
                    t_rel = 0
                else:
                    t_rel = t - start
                t0 = time.perf_counter()
                # Warnings and errors of a method are results, reported, not the end of the run.
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    try:
                        if isinstance(cfg, TrueMatches):
                            tm = true_matches(first["cam1"], truth["cam1"], rig, cfg.percentile)
                            res = estimate(g1, g2, rig, cfg.config, t=t_rel, matches=tm)
                        else:
                            res = estimate(g1, g2, rig, cfg, t=t_rel)
                    except Exception as exc:
                        res = _FailedResult()
                        msg = str(exc).splitlines()[0] if str(exc) else ""
                        results.notes.append(
                            f"{name} failed on frame pair {t} -> {t + 1}: "
                            f"{type(exc).__name__}: {msg} (scored as no points)"
                        )
                seconds = time.perf_counter() - t0
                if caught:
                    w0 = caught[0]
                    results.notes.append(
                        f"{name} emitted {len(caught)} warning(s) on frame pair {t} -> {t + 1}; "
                        f"first: {w0.category.__name__}: {w0.message} "
                        f"({Path(w0.filename).name}:{w0.lineno})"
                    )
                results.times[name].append(seconds)
                for stage, sec in (getattr(res, "timings", None) or {}).items():
                    results.stages[name][stage] += float(sec)
                cols = res.columns
                for cam in CAMERAS:
                    x, y, est = _omniflow_points(cols, cam)
                    err = _score_flow(est, x, y, truth[cam])
                    results.flow[(name, "own", cam)].append(err)
                    row = _flow_row(t, name, "own", cam, err, seconds)
                    # The baselines at exactly these points, for a like-for-like column.
                    for b in baselines:
                        berr = _score_flow(dense[b][cam].at(x, y), x, y, truth[cam])
                        results.flow[(b, f"@{name}", cam)].append(berr)
                        row[f"{b}_epe_median_same_points"] = stats(berr["epe"])["median"]
                    if vi == 0:
                        default_pts[cam] = (x, y)
                        if results.snapshot is None:
                            tr = sample_truth(truth[cam], x, y, channels=FLOW_TRUTH)
                            snap_points[cam] = {
                                "x": x,
                                "y": y,
                                "dx": est["dx"],
                                "dy": est["dy"],
                                "gt_dx": tr["gt.flow.dx"],
                                "gt_dy": tr["gt.flow.dy"],
                            }
                    results.rows.append(row)
                srow = _score_stereo(results, name, cols, res, truth["cam1"], t)
                drow = _score_derived(
                    results, name, cols, truth["cam1"], t, robot_poses, object_poses
                )
                results.rows[-2].update(srow)
                results.rows[-2].update(drow)
                bar.update(1)

            # Baselines at the default variant's points: the like-for-like comparison.
            if default_name is not None:
                for b in baselines:
                    for cam in CAMERAS:
                        x, y = default_pts[cam]
                        err = _score_flow(dense[b][cam].at(x, y), x, y, truth[cam])
                        results.flow[(b, "omniflow points", cam)].append(err)
                        results.rows.append(
                            _flow_row(t, b, "omniflow points", cam, err, dense[b][cam].seconds)
                        )

            if results.snapshot is None:
                pan = bl.unwarp_u8(first["cam1"], units["cam1"])
                results.snapshot = FramePair(
                    t=t,
                    images={cam: first[cam] for cam in CAMERAS},
                    truth={
                        cam: {k: v for k, v in truth[cam].items() if k.startswith("gt.")}
                        for cam in CAMERAS
                    },
                    dense={
                        b: {cam: _dense_array(dense[b][cam], truth[cam]) for cam in CAMERAS}
                        for b in baselines
                    },
                    points=snap_points,
                    panorama=pan,
                )
    finally:
        bar.close()
    results.notes = _compact_notes(results.notes)
    return results


def _compact_notes(notes: list[str]) -> list[str]:
    """Merge notes that differ only in their frame pair: '... on frame pairs 0 -> 1, 1 -> 2 ...'."""
    import re

    merged: dict[str, list[str]] = {}
    for note in notes:
        m = re.search(r" on frame pair (\d+ -> \d+)", note)
        key = note if m is None else note.replace(m.group(0), " on frame pair(s) {}")
        merged.setdefault(key, []).append("" if m is None else m.group(1))
    return [
        key.replace("{}", ", ".join(p for p in pairs if p)) if "{}" in key else key
        for key, pairs in merged.items()
    ]


def _dense_array(field_: Any, truth: dict[str, NDArray]) -> NDArray:
    """The image-plane flow (H, W, 2) of a baseline (panorama flow mapped back)."""
    if isinstance(field_, bl.DenseFlow):
        return field_.flow
    h, w = truth["gt.valid"].shape
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    est = field_.at(xx.ravel(), yy.ravel())
    return np.stack([est["dx"].reshape(h, w), est["dy"].reshape(h, w)], axis=-1)


def _is_paper_config(cfg: Any) -> bool:
    try:
        from omniflow.pipeline import OmniFlowConfig

        return bool(cfg == OmniFlowConfig.paper())
    except (ImportError, AttributeError, TypeError):
        return False


def _config_dict(cfg: Any) -> dict[str, Any]:
    if isinstance(cfg, TrueMatches):
        out = _config_dict(cfg.config)
        out["match_method"] = "truth"
        out["true_matches_percentile"] = cfg.percentile
        return out
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        out[f.name] = v if isinstance(v, int | float | str | bool) or v is None else repr(v)
    return out


def _flow_row(t: int, method: str, points: str, cam: str, err: dict, seconds: float) -> dict:
    s = flow_summary(err, err["noc"])
    row: dict[str, Any] = {
        "frame": t,
        "method": method,
        "points": points,
        "camera": cam,
        "n_points": int(err["n_points"]),
        "n_with_truth": s["all"]["n"],
        "epe_median": s["all"]["epe"]["median"],
        "epe_mean": s["all"]["epe"]["mean"],
        "epe_p90": s["all"]["epe"]["p90"],
        "dh_median": s["all"]["dh"]["median"],
        "hdtheta_median": s["all"]["hdtheta"]["median"],
        "ae_median_deg": s["all"]["ae"]["median"],
        "out1": s["all"]["out1"],
        "out3": s["all"]["out3"],
        "noc_n": s["noc"]["n"],
        "noc_epe_median": s["noc"]["epe"]["median"],
        "occ_n": s["occ"]["n"],
        "occ_epe_median": s["occ"]["epe"]["median"],
        "speed_median_px": stats(err["speed"])["median"],
        "time_s": seconds,
    }
    return row


def _score_stereo(
    results: Results, name: str, cols: dict, res: Any, truth: dict[str, NDArray], t: int
) -> dict[str, Any]:
    x = np.asarray(cols["x"], np.float64)
    y = np.asarray(cols["y"], np.float64)
    tr = sample_truth(truth, x, y, channels=STEREO_TRUTH)
    has = tr["bilinear_ok"] & (tr["gt.stereo.valid"] > 0.5)
    err = stereo_errors(
        {
            "h2": np.asarray(cols["h2"])[has],
            "r": np.asarray(cols["r"])[has],
            "h": np.asarray(cols["h"])[has],
        },
        {"h_other": tr["gt.stereo.h_other"][has], "r": tr["gt.r"][has], "h": tr["gt.h"][has]},
    )
    results.stereo[name].append(err)
    counts = results.stereo_counts[name]
    counts["matched"] += int(x.size)
    counts["valid_pixels"] += int(np.count_nonzero(truth["gt.valid"] > 0.5))
    sig = _significant(res)
    n_sig = None
    if isinstance(sig, tuple):
        st = sample_truth(
            truth, sig[0], sig[1], channels=("gt.valid", "gt.object", "gt.stereo.valid")
        )
        n_sig = int(np.count_nonzero(st["gt.stereo.valid"] > 0.5))
    elif isinstance(sig, int):
        n_sig = sig
    if n_sig is None:
        counts["significant_unknown"] = 1
    else:
        counts["significant_valid"] += n_sig
    s = stereo_summary(
        err,
        n_matched=x.size,
        n_significant_valid=n_sig,
        n_valid_pixels=int(np.count_nonzero(truth["gt.valid"] > 0.5)),
    )
    return {
        "stereo_n": s["all"]["n"],
        "stereo_outliers": s["all"]["outliers"],
        "match_rate": s["match_rate"],
        "density": s["density"],
        "rel_r_median": s["all"]["rel_r"]["median"],
        "err_h_median_m": s["all"]["err_h"]["median"],
    }


def _score_derived(
    results: Results,
    name: str,
    cols: dict,
    truth: dict[str, NDArray],
    t: int,
    robot_poses: list | None,
    object_poses: dict[int, list],
) -> dict[str, Any]:
    """dr/dt and time to contact against the objects' known motion; odometry vs the robot's."""
    if robot_poses is None or len(robot_poses) <= t + 1:
        return {}
    x = np.asarray(cols["x"], np.float64)
    y = np.asarray(cols["y"], np.float64)
    tr = sample_truth(truth, x, y, channels=STEREO_TRUTH)
    has = tr["bilinear_ok"] & np.isfinite(np.asarray(cols["dr_dt"], np.float64))
    world = np.stack([tr["gt.X"], tr["gt.Y"], tr["gt.Z"]], axis=1)[has]
    ids = np.rint(tr["gt.object"][has]).astype(np.int64)
    poses_t = {k: v[t] for k, v in object_poses.items() if len(v) > t + 1}
    poses_t1 = {k: v[t + 1] for k, v in object_poses.items() if len(v) > t + 1}
    mot = point_motion(world, ids, poses_t, poses_t1, robot_poses[t], robot_poses[t + 1])
    dr_est = np.asarray(cols["dr_dt"], np.float64)[has]
    r_est = np.asarray(cols["r"], np.float64)[has]
    rec: dict[str, Any] = {
        "frame": t,
        "dr_err": np.abs(dr_est - mot["dr_dt"]),
        "dr_true": mot["dr_dt"],
        "ids": ids,
    }
    # Time to contact of approaching points (true dr/dt below -0.1 % of r per frame).
    approaching = mot["dr_dt"] < -1e-3 * mot["r0"]
    ttc_est = _time_to_contact(r_est, dr_est)
    with np.errstate(divide="ignore", invalid="ignore"):
        rec["ttc_relerr"] = (
            np.abs(ttc_est[approaching] - mot["ttc"][approaching]) / mot["ttc"][approaching]
        )
    rec["ttc_objects"] = {}
    for oid in np.unique(ids[approaching]):
        sel = approaching & (ids == oid)
        rec["ttc_objects"][int(oid)] = (
            float(np.median(mot["ttc"][sel])),
            float(np.median(ttc_est[sel])),
            int(sel.sum()),
        )
    # Odometry: robust fit of the robot's yaw rate and velocity to all matched points.
    truth_motion = robot_motion(robot_poses[t], robot_poses[t + 1])
    rec["robot_true"] = truth_motion
    fits = _odometry(cols)
    if fits is not None:
        rec["robot_est"] = fits
        for label, fit in fits.items():
            rec[f"odo_{label}_w_err"] = abs(fit["w"] - truth_motion["w"])
            rec[f"odo_{label}_v_err"] = math.hypot(
                fit["vx"] - truth_motion["vx"], fit["vy"] - truth_motion["vy"]
            )
    results.derived[name].append(rec)
    out = {
        "drdt_err_median": stats(rec["dr_err"])["median"],
        "ttc_relerr_median": stats(rec["ttc_relerr"])["median"],
    }
    for key in ("odo_both_w_err", "odo_both_v_err", "odo_tangential_w_err", "odo_tangential_v_err"):
        if key in rec:
            out[key] = rec[key]
    return out


def _time_to_contact(r: NDArray, dr_dt: NDArray) -> NDArray:
    from omniflow.applications import time_to_contact

    return np.asarray(time_to_contact(r, dr_dt), dtype=np.float64)


def _odometry(cols: dict) -> dict[str, dict[str, float]] | None:
    """omniflow.applications.odometry on all matched points: both flow components,
    and the bearing rates alone (omni flow's radial component is the noisier one)."""
    from omniflow.applications import odometry

    theta = np.asarray(cols["theta"], np.float64)
    r = np.asarray(cols["r"], np.float64)
    dr = np.asarray(cols["dr_dt"], np.float64)
    dth = np.asarray(cols["dtheta_dt"], np.float64)
    ok = np.isfinite(theta) & np.isfinite(r) & np.isfinite(dr) & np.isfinite(dth) & (r > 0)
    if ok.sum() < 10:
        return None
    if ok.sum() > ODOMETRY_POINTS:  # a fixed random subset keeps the robust fit fast
        keep = np.random.default_rng(0).choice(np.flatnonzero(ok), ODOMETRY_POINTS, replace=False)
        ok = np.zeros_like(ok)
        ok[keep] = True
    out = {}
    for label, radial in (("both", dr[ok]), ("tangential", None)):
        fit = odometry(theta[ok], r[ok], dth[ok], radial)
        out[label] = {
            "w": float(fit.w),
            "vx": float(fit.V_x),
            "vy": float(fit.V_y),
            "inliers": float(fit.inlier_fraction),
        }
    return out
