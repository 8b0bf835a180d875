"""The run loop: every omniflow variant, baseline and external method on every frame pair.

The harness reads the dataset only through :func:`omniflow.io.dataset.open_dataset`
(``dataset.json`` and the EXR channels), so any generator that writes that
contract is scored the same way. The pieces it strings together each live in
their own module: the images (:mod:`validation.inputs`), the omniflow rows
(:mod:`validation.variants`), the baselines (:mod:`validation.baselines`) and
other methods' outputs (:mod:`validation.external`), the scorers
(:mod:`validation.scoring_flow`, :mod:`validation.scoring_stereo`,
:mod:`validation.scoring_derived`) and the container they fill
(:mod:`validation.results`).

Units. omniflow estimates velocities per frame interval (pixels/frame,
radians/frame, metres/frame); the ground truth is the displacement of each
material point from frame t to t + 1 (pixels). Both are per frame and are
compared directly; for motions of a pixel or more the first-order velocity
and the finite displacement differ, which shows in the large-motion scenes.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import baselines as bl
from .calibration_sigma import has_sigma, sigma_errors
from .densify import interpolate_flow
from .external import ExternalOutput
from .inputs import CAMERAS, InputError, Inputs, camera_model
from .metrics import stats
from .results import FramePair, MethodInfo, Results
from .sampling import sample_truth
from .scoring_derived import meta_poses, moving_objects, score_derived, ttc_scores
from .scoring_flags import score_flags
from .scoring_flow import FLOW_TRUTH, flow_row, omniflow_points, score_dense, score_flow
from .scoring_stereo import score_stereo
from .variants import (
    VARIANT_CHOICES,
    Registered,
    TrueMatches,
    config_dict,
    is_paper_config,
    omniflow_variants,
    told_rig,
    true_matches,
    variant_name,
)

__all__ = [
    "VARIANT_CHOICES",
    "FramePair",
    "InputError",
    "Results",
    "TrueMatches",
    "omniflow_variants",
    "run_validation",
    "true_matches",
    "ttc_scores",
    "variant_name",
]


#: Columns the harness reads from OmniFlowResult.columns.
RESULT_COLUMNS = ("x", "y", "theta", "h1", "h2", "r", "h", "dh1_dt", "dtheta_dt", "dr_dt", "dx",
                  "dy", "x2", "y2", "dh2_dt", "dx2", "dy2")  # fmt: skip


class _FailedResult:
    """Stands in for the result of an estimate that raised: no points."""

    def __init__(self) -> None:
        self.columns = {k: np.zeros(0) for k in RESULT_COLUMNS}
        self.timings: dict[str, float] = {}
        self.n_significant = None


# -- inputs ---------------------------------------------------------------------------


def _window(t: int, count: int, need: int) -> tuple[int, int]:
    """First frame and length of a window of ``need`` frames that holds t and t + 1."""
    start = max(0, min(t, count - need))
    return start, min(need, count - start)


# -- scoring helpers -------------------------------------------------------------------


# -- the run ----------------------------------------------------------------------------


def run_validation(
    dataset_dir: str | Path,
    *,
    variants: str | Sequence[tuple[str, Any]] = "all",
    baselines: Iterable[str] = bl.DEFAULT_BASELINES,
    frames: Sequence[int] | None = None,
    progress: bool = True,
    estimate: Callable[..., Any] | None = None,
    external: Sequence[ExternalOutput] = (),
    camera: Sequence[str] = (),
    partial: bool = False,
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
    external : sequence of ExternalOutput
        Outputs of other methods to score (:mod:`validation.external`).
    camera : sequence of "KEY=VALUE"
        Camera-model overrides applied when the images are formed (:mod:`validation.inputs`).
    partial : bool
        Score the complete pairs of an incomplete dataset (else refuse it, saying how
        much is missing).
    """
    from tqdm import tqdm

    from omniflow.io.dataset import open_dataset

    if estimate is None:
        from omniflow.pipeline import estimate

    ds = open_dataset(dataset_dir)
    done = set(ds.frames_done())
    pairs = _pairs(ds, dataset_dir, done, frames, partial)
    _check_files(ds, sorted({k for t in pairs for k in (t, t + 1)}))
    vlist = omniflow_variants(variants) if isinstance(variants, str) else list(variants)
    baselines = list(baselines)
    for b in baselines:
        if b not in bl.BASELINES:
            raise InputError(f"unknown baseline {b!r}; expected some of {bl.BASELINES}")

    for ext in external:
        ext.check(pairs)
    _check_told_rigs(ds, vlist)
    meta = ds.meta
    auto = not isinstance(meta.get("camera"), dict) and not any(
        str(c).split("=", 1)[0].strip().removeprefix("camera.") == "exposure" for c in camera
    )
    model = camera_model(meta, camera, where=str(ds.dir / "dataset.json"))
    inputs = Inputs(ds, model, auto_exposure=auto)
    results = _new_results(ds, dataset_dir, pairs, vlist, baselines, external)
    need = 3 if any(_dct3d(c) for _, c in vlist) else 2
    run = _Run(
        ds=ds,
        rig=ds.rig,
        inputs=inputs,
        results=results,
        vlist=vlist,
        baselines=baselines,
        ext_dense=[e for e in external if e.kind == "dense"],
        ext_points=[e for e in external if e.kind == "points"],
        estimate=estimate,
        pairs=pairs,
        done=done,
        need=min(need, len(done)),
        units={"cam1": ds.rig.cam1, "cam2": ds.rig.cam2},
        poses=meta_poses(meta),
    )
    steps = len(pairs) * (len(vlist) + len(baselines) + len(external))
    run.bar = tqdm(
        total=steps,
        desc=f"omnivalidate {results.dataset['scene']}",
        unit="run",
        disable=not progress,
        leave=False,
    )
    try:
        for t in pairs:
            _score_pair(run, t)
    finally:
        run.bar.close()
    results.notes = _compact_notes(results.notes)
    results.dataset["camera"] = None if inputs.camera is None else inputs.camera.to_dict()
    results.dataset["images"] = inputs.describe()
    return results


def _check_told_rigs(ds: Any, vlist: Sequence[tuple[str, Any]]) -> None:
    """InputError where a row's rig file (``--registration FILE``) is not this dataset's
    camera: another image size, or another d, R or s."""
    for _, cfg in vlist:
        rig = cfg.rig if isinstance(cfg, Registered) else None
        if rig is None:
            continue
        for cam in CAMERAS:
            mine, theirs = getattr(ds.rig, cam), getattr(rig, cam)
            if (mine.width, mine.height) != (theirs.width, theirs.height):
                raise InputError(
                    f"--registration {cfg.rig_file}: {cam} is {theirs.width} x "
                    f"{theirs.height} px, the dataset's {mine.width} x {mine.height}; "
                    "calibrate at the dataset's resolution"
                )
        got, want = (rig.d, rig.R, rig.s), (ds.rig.d, ds.rig.R, ds.rig.s)
        if not np.allclose(got, want, rtol=1e-6, atol=0.0):
            raise InputError(f"--registration {cfg.rig_file}: d, R, s = {got}, the dataset's "
                             f"{want}; expected the dataset's rig")  # fmt: skip


def _check_files(ds: Any, frames: Sequence[int]) -> None:
    """InputError naming the first camera PNG, mask or ``.flo`` of ``frames`` that does not
    decode (omnisim.check_files): a damaged dataset is refused, not scored."""
    from omnisim.check_files import dataset_file_problems

    problems, _ = dataset_file_problems(ds, frames)
    if problems:
        path, why = next(iter(problems.items()))
        more = f" (and {len(problems) - 1} more files)" if len(problems) > 1 else ""
        raise InputError(f"{path}: {why}{more}; re-render the frame or run omnisim check")


def _pairs(
    ds: Any, dataset_dir: str | Path, done: set[int], frames: Sequence[int] | None, partial: bool
) -> list[int]:
    """The frame pairs t -> t + 1 to score; InputError where the dataset cannot give them."""
    if len(done) < ds.frame_count and not partial and frames is None:
        missing = sorted(set(range(ds.frame_count)) - done)
        shown = ", ".join(str(k) for k in missing[:10]) + (" ..." if len(missing) > 10 else "")
        raise InputError(
            f"{dataset_dir}: incomplete dataset: {len(missing)} of {ds.frame_count} frames "
            f"missing ({shown}); finish the render, or pass --partial to score the "
            "complete pairs"
        )
    pairs = [t for t in range(ds.frame_count - 1) if t in done and t + 1 in done]
    if frames is not None:
        wanted = sorted(set(int(t) for t in frames))
        missing = [t for t in wanted if t not in pairs]
        if missing:
            raise InputError(f"{dataset_dir}: no complete frame pair t -> t + 1 for t = {missing}")
        pairs = wanted
    if not pairs:
        raise InputError(f"{dataset_dir}: no complete frame pair (needs two consecutive frames)")
    return pairs


def _new_results(
    ds: Any,
    dataset_dir: str | Path,
    pairs: list[int],
    vlist: list[tuple[str, Any]],
    baselines: list[str],
    external: Sequence[ExternalOutput],
) -> Results:
    """The empty container: the dataset's description and one MethodInfo per row."""
    meta, rig = ds.meta, ds.rig
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
            "moving_objects": moving_objects(meta),
            "camera": None,
        },
        methods=[
            MethodInfo(name, "omniflow", config_dict(cfg), i == 0, is_paper_config(cfg))
            for i, (name, cfg) in enumerate(vlist)
        ]
        + [MethodInfo(b, "baseline") for b in baselines]
        + [
            MethodInfo(
                e.name,
                "baseline" if e.kind == "dense" else "external",
                {"method_output": str(e.dir), "format": e.kind},
            )
            for e in external
        ],
    )
    names = [m.name for m in results.methods]
    if len(set(names)) != len(names):
        raise InputError(f"two rows share a name in {names}; give --method-name")
    return results


@dataclass
class _Run:
    """What every frame pair of one run reads: the dataset, the rows and the container."""

    ds: Any
    rig: Any
    inputs: Inputs
    results: Results
    vlist: list[tuple[str, Any]]
    baselines: list[str]
    ext_dense: list[ExternalOutput]
    ext_points: list[ExternalOutput]
    estimate: Callable[..., Any]
    pairs: list[int]
    done: set[int]
    need: int
    units: dict[str, Any]
    poses: tuple[Any, Any]
    bar: Any = None


@dataclass
class _Pair:
    """One frame pair's truth and images: grey windows for omniflow, uint8 for OpenCV."""

    t: int
    start: int
    truth: dict[str, dict[str, NDArray]]
    grey: dict[str, list[NDArray]]
    first: dict[str, NDArray]
    second: dict[str, NDArray]


def _load_pair(run: _Run, t: int) -> _Pair:
    """The truth of frame t and the images of the window that holds t and t + 1."""
    ds, units = run.ds, run.units
    truth = {cam: ds.read_frame(t, cam) for cam in CAMERAS}
    for cam in CAMERAS:
        truth[cam]["_centre"] = (units[cam].x_c, units[cam].y_c)  # type: ignore[assignment]
    start, length = _window(t, ds.frame_count, run.need)
    window = list(range(start, start + length))
    if not all(k in run.done for k in window):
        window = [t, t + 1]
        start = t
    made = {
        cam: [run.inputs.frame(k, cam, truth[cam] if k == t else None) for k in window]
        for cam in CAMERAS
    }
    run.inputs.drop_before(start)
    u8 = {cam: [f[0] for f in made[cam]] for cam in CAMERAS}
    grey = {cam: [f[1] for f in made[cam]] for cam in CAMERAS}
    first = {cam: u8[cam][t - start] for cam in CAMERAS}
    second = {cam: u8[cam][t + 1 - start] for cam in CAMERAS}
    return _Pair(t, start, truth, grey, first, second)


def _score_pair(run: _Run, t: int) -> None:
    """Score every row on the pair t -> t + 1 into ``run.results``."""
    results = run.results
    pair = _load_pair(run, t)
    truth = pair.truth
    # Baselines first: their dense fields are also sampled at every variant's points.
    dense = _score_baselines(run, pair)
    default_pts: dict[str, tuple[NDArray, NDArray]] = {}
    snap_points: dict[str, dict[str, NDArray]] = {}
    rows = [*run.vlist, *((e.name, e) for e in run.ext_points)]
    for vi, (name, cfg) in enumerate(rows):
        run.bar.set_postfix_str(f"t={t} {name}")
        res, seconds = _estimate_row(run, pair, name, cfg)
        results.times[name].append(seconds)
        for stage, sec in res.timings.items():
            results.stages[name][stage] += float(sec)
        cols = res.columns
        for cam in CAMERAS:
            x, y, est = omniflow_points(cols, cam)
            err = score_flow(est, x, y, truth[cam])
            results.flow[(name, "own", cam)].append(err)
            # The same flow made dense (validation.densify), scored at every valid pixel.
            field = interpolate_flow(pair.first[cam], x, y, est["dx"], est["dy"])
            results.flow[(name, "interpolated", cam)].append(score_dense(None, truth[cam], field))
            row = flow_row(t, name, "own", cam, err, seconds)
            # The baselines at exactly these points, for a like-for-like column.
            for b in dense:
                berr = score_flow(dense[b][cam].at(x, y), x, y, truth[cam])
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
        _score_monocular(results, name, res, truth["cam1"], dense)
        sigma = getattr(res, "sigma", None)
        if has_sigma(sigma):  # the predicted sigmas against the errors (calibration)
            results.sigma[name].append(sigma_errors(cols, sigma, truth))
        srow = score_stereo(results, name, cols, res, truth["cam1"], t)
        drow = score_derived(results, name, cols, truth["cam1"], t, *run.poses)
        frow = score_flags(results, name, cols, truth, t, run.rig, *run.poses)
        results.rows[-2].update(srow)
        results.rows[-2].update(drow)
        results.rows[-2].update(frow)
        run.bar.update(1)

    # Baselines at the default variant's points: the like-for-like comparison.
    if run.vlist:
        for b in dense:
            for cam in CAMERAS:
                x, y = default_pts[cam]
                err = score_flow(dense[b][cam].at(x, y), x, y, truth[cam])
                results.flow[(b, "omniflow points", cam)].append(err)
                results.rows.append(
                    flow_row(t, b, "omniflow points", cam, err, dense[b][cam].seconds)
                )

    if results.snapshot is None:
        pan = bl.unwarp_u8(pair.first["cam1"], run.units["cam1"])
        results.snapshot = FramePair(
            t=t,
            images={cam: pair.first[cam] for cam in CAMERAS},
            truth={
                cam: {k: v for k, v in truth[cam].items() if k.startswith("gt.")} for cam in CAMERAS
            },
            dense={
                b: {cam: _dense_array(dense[b][cam], truth[cam]) for cam in CAMERAS} for b in dense
            },
            points=snap_points,
            panorama=pan,
        )


def _score_baselines(run: _Run, pair: _Pair) -> dict[str, dict[str, Any]]:
    """Run and score each dense baseline (and dense external output) at every valid pixel."""
    results, units, truth, t = run.results, run.units, pair.truth, pair.t
    dense: dict[str, dict[str, Any]] = {}
    for b in [*run.baselines, *run.ext_dense]:
        if isinstance(b, ExternalOutput):
            shape = truth["cam1"]["gt.valid"].shape
            fields = {cam: b.dense(t, cam, units[cam], shape) for cam in CAMERAS}
            b = b.name
        else:
            if t == run.pairs[0]:  # untimed warm-up: see _estimate_row
                bl.dense_baseline(b, pair.first["cam1"], pair.second["cam1"], units["cam1"])
            fields = {
                cam: bl.dense_baseline(b, pair.first[cam], pair.second[cam], units[cam])
                for cam in CAMERAS
            }
        run.bar.set_postfix_str(f"t={t} {b}")
        dense[b] = fields
        results.times[b].append(sum(f.seconds for f in fields.values()))
        for cam in CAMERAS:
            f = fields[cam]
            flow = f.flow if isinstance(f, bl.DenseFlow) else None
            err = score_dense(f.at, truth[cam], flow)
            results.flow[(b, "dense", cam)].append(err)
            results.rows.append(flow_row(t, b, "dense", cam, err, f.seconds))
        run.bar.update(1)
    return dense


def _dct3d(cfg: Any) -> bool:
    """Whether a row's config fits a 3-D DCT over time (a stand-in config never does)."""
    return getattr(getattr(cfg, "fit", None), "temporal", "") == "dct3d"


def _estimate_row(run: _Run, pair: _Pair, name: str, cfg: Any) -> tuple[Any, float]:
    """One row's result on the pair and its seconds; a failure is a note and no points."""
    from omniflow.pipeline import OmniFlowConfig

    results, estimate, t, start = run.results, run.estimate, pair.t, pair.start
    rig = told_rig(cfg, run.rig)  # --registration: what omniflow is told about the rig
    cfg = cfg.config if isinstance(cfg, Registered) else cfg
    g1 = pair.grey["cam1"]
    g2 = pair.grey["cam2"]
    if not _dct3d(cfg):
        g1, g2 = g1[t - start : t - start + 2], g2[t - start : t - start + 2]
        t_rel = 0
    else:
        t_rel = t - start
    if t == run.pairs[0] and isinstance(cfg, OmniFlowConfig):
        # Untimed warm-up: a configuration's first estimate() in a process loads
        # its compiled kernels (0.5 s at 512 px against 0.05 s warm), which would
        # be most of the time per frame of a run of one or two pairs. A failure
        # here shows again, and is reported, in the timed call. (Not for test
        # stand-ins such as the truth oracle, which count their calls.)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                estimate(g1, g2, rig, cfg, t=t_rel)
            except Exception:  # broad: the timed call below reports it
                pass
    t0 = time.perf_counter()
    # Warnings and errors of a method are results, reported, not the end of the run.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if isinstance(cfg, ExternalOutput):
                res = cfg.points(t, rig)
            elif isinstance(cfg, TrueMatches):
                tm = true_matches(pair.grey["cam1"][t - start], pair.truth["cam1"], rig,
                                  cfg.percentile, band=cfg.config.band)  # fmt: skip
                res = estimate(g1, g2, rig, cfg.config, t=t_rel, matches=tm)
            else:
                res = estimate(g1, g2, rig, cfg, t=t_rel)
        except InputError:
            raise
        except Exception as exc:  # broad: a method's failure is a result, scored as no points
            res = _FailedResult()
            msg = str(exc).splitlines()[0] if str(exc) else ""
            results.notes.append(
                f"{name} failed on frame pair {t} -> {t + 1}: "
                f"{type(exc).__name__}: {msg} (scored as no points)"
            )
    seconds = math.nan if isinstance(cfg, ExternalOutput) else time.perf_counter() - t0
    if caught:
        w0 = caught[0]
        results.notes.append(
            f"{name} emitted {len(caught)} warning(s) on frame pair {t} -> {t + 1}; "
            f"first: {w0.category.__name__}: {w0.message} "
            f"({Path(w0.filename).name}:{w0.lineno})"
        )
    return res, seconds


def _score_monocular(
    results: Results, name: str, res: Any, truth: dict[str, NDArray], dense: dict
) -> None:
    """Score a row's cam1-only flow (``OmniFlowConfig.monocular_gap``) as points
    ``monocular`` of cam1, and the dense baselines at the same points."""
    config = getattr(res, "config", None)
    if config is None or getattr(config, "monocular_gap", None) is None:
        return
    from omniflow.result import MONOCULAR_COLUMNS

    mono = res.monocular or {k: np.zeros(0) for k in MONOCULAR_COLUMNS}
    x, y = np.asarray(mono["x"], np.float64), np.asarray(mono["y"], np.float64)
    est = {"dx": mono["dx"], "dy": mono["dy"], "dh": mono["dh1_dt"],
           "hdtheta": np.asarray(mono["h1"]) * np.asarray(mono["dtheta_dt"])}  # fmt: skip
    results.flow[(name, "monocular", "cam1")].append(score_flow(est, x, y, truth))
    for b in dense:
        berr = score_flow(dense[b]["cam1"].at(x, y), x, y, truth)
        results.flow[(b, f"@{name}:monocular", "cam1")].append(berr)


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
