"""Choose omniflow's sigma constants on a suite's train split; report the test split.

``python -m validation.sigma_fit SUITE.toml RENDERS [--methods default,dense]
[--cache DIR]`` reads each scene's render (``RENDERS/NAME``, as ``omnivalidate suite``
leaves them in ``OUT/renders``), forms the camera images as the harness does
(:class:`validation.inputs.Inputs`), runs each omniflow preset on every frame pair with
the raw prediction (every :class:`omniflow.solve.sigma.SigmaModel` constant at its
neutral value) and keeps, per point, the error of each quantity with the raw terms of
its prediction. On the train split it then chooses, per preset's solver:

* flow: ``flow_share`` and ``flow_floor`` from a grid, each with the ``flow_scale``
  that puts 95 % of the train points (both cameras) within 2 sigma; kept: the pair
  with the smallest sum of the worst deviation of a sigma bin's 2-sigma share from
  95 % (a flat reliability curve) and the mean deviation of a train scene's share
  (the same calibration on every scene), the smaller median sigma on ties;
* range: ``range_score`` and ``range_floor`` the same way, with ``range_scale``.

It prints the constants and the train and test splits' shares within 1 and 2 sigma per
camera and for range, pooled and per scene (docs/decisions/confidence.md).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from omniflow.config import OmniFlowConfig
from omniflow.io.dataset import open_dataset
from omniflow.pipeline import estimate
from omniflow.solve import sigma as sigma_mod

from .calibration_sigma import QUANTITIES, sigma_errors, within
from .inputs import CAMERAS, Inputs, camera_model
from .suite import load_suite

SHARES = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0)
FLOORS = (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)  # px
SCORE_TERMS = (0.0, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0)  # px^2 per unit (1 - score)
RANGE_FLOORS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)  # px
TARGET = 0.95


def collect(dataset: Path, preset: str, pairs: int | None = None) -> dict[str, np.ndarray]:
    """Per point of the first ``pairs`` frame pairs (all by default): errors and the raw
    terms of each prediction."""
    ds = open_dataset(dataset)
    meta = ds.meta
    inputs = Inputs(ds, camera_model(meta), auto_exposure=not isinstance(meta.get("camera"), dict))
    cfg = OmniFlowConfig.preset(preset)
    rig = ds.rig
    parts: dict[str, list] = {}
    done = sorted(ds.frames_done())
    for t in done[:-1][:pairs]:
        truth = {cam: ds.read_frame(t, cam) for cam in CAMERAS}
        g = {cam: [inputs.grey(k, cam, truth[cam] if k == t else None) for k in (t, t + 1)]
             for cam in CAMERAS}  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = estimate(g["cam1"], g["cam2"], rig, cfg)
        if len(res) == 0:
            continue
        cols = res.columns
        errs = sigma_errors(cols, {k: np.ones(len(res)) for k in res.sigma}, truth)
        raw = _raw_terms(cols, res.sigma, rig)
        for q, keep in _masks(cols, truth).items():  # the raw terms at the same points
            # only finite sigmas, as the harness scores (the eq. 14-flagged points' cam2
            # and range sigmas are inf: omniflow.result.confident)
            ok = np.isfinite(res.sigma[QUANTITIES[q][0]][keep])
            for name, v in raw.items():
                parts.setdefault(f"{q}.{name}", []).append(v[keep][ok])
            parts.setdefault(f"{q}.err", []).append(errs[q]["err"][ok])
    return {k: np.concatenate(v) for k, v in parts.items()}


def _masks(cols, truth):
    """The points :func:`sigma_errors` keeps per quantity, found by passing each point's
    index as its 'sigma'."""
    idx = {k: np.arange(np.size(cols["x"]), dtype=np.float64) for k in sigma_mod.SIGMA_COLUMNS}
    return {q: rec["sigma"].astype(np.intp) for q, rec in sigma_errors(cols, idx, truth).items()}


def _raw_terms(cols, raw_sigma, rig):
    h1, h2 = np.asarray(cols["h1"]), np.asarray(cols["h2"])
    k = h2 / h1
    dr = (rig.d + np.asarray(cols["r"])) ** 2 / (rig.s * rig.cam2.v)
    return {
        "ls1": raw_sigma["sigma_flow1"] ** 2,
        "ls2": raw_sigma["sigma_flow2"] ** 2,
        "speed1": np.hypot(cols["dx"], cols["dy"]),
        "speed2": np.hypot(cols["dx2"], cols["dy2"]),
        "k": k,
        "coupled": np.asarray(cols["coupled"], np.float64),
        "loc": (raw_sigma["sigma_r"] / dr) ** 2,
        "score": np.clip(np.asarray(cols["score"], np.float64), -1.0, 1.0),
        "dr": dr,
    }


def flow_raw(d: dict, cam: str, share: float, floor: float) -> np.ndarray:
    """The unscaled flow sigma of :func:`omniflow.solve.sigma.sigmas` from the raw terms."""
    q = f"{cam}."
    s1 = np.sqrt(d[q + "ls1"] + (share * d[q + "speed1"]) ** 2 + floor**2)
    if cam == "cam1":
        return s1
    return np.where(d[q + "coupled"] > 0.5, d[q + "k"] * s1, np.inf)  # flagged: inf


def range_raw(d: dict, score_term: float, floor: float) -> np.ndarray:
    return d["range.dr"] * np.sqrt(
        d["range.loc"] + score_term * (1.0 - d["range.score"]) + floor**2
    )


def _scale(err: np.ndarray, raw: np.ndarray) -> float:
    """The scale putting TARGET of the points within 2 scaled sigma (a point with no
    finite sigma counts as outside)."""
    ratio = err / np.where(raw > 0, raw, np.nan)
    ratio = np.where(np.isfinite(ratio), ratio, np.inf)
    return float(np.quantile(ratio, TARGET) / 2.0) if ratio.size else 1.0


def _flatness(err, sig, bins=8):
    """The worst deviation of a sigma bin's 2-sigma share from TARGET."""
    order = np.argsort(np.where(np.isfinite(sig), sig, np.inf))
    return max(abs(within(err[p], sig[p], 2.0) - TARGET) for p in np.array_split(order, bins))


def _scene_spread(scenes, shares):
    """The mean deviation of the train scenes' 2-sigma shares from TARGET (scenes with
    at least MIN_POINTS points)."""
    dev = [abs(shares(d) - TARGET) for d in scenes]
    return float(np.mean(dev)) if dev else 0.0


MIN_POINTS = 50


def fit(train: list[dict]) -> dict[str, float]:
    """The constants of one solver from the train split's points (module docstring): per
    candidate, the scale that puts TARGET of the pooled points within 2 sigma; kept, the
    smallest sum of the worst sigma bin's and the mean scene's deviation from TARGET."""
    d = {k: np.concatenate([t[k] for t in train if k in t]) for k in train[0]}
    big = [t for t in train if t["cam1.err"].size >= MIN_POINTS]
    err = np.concatenate([d["cam1.err"], d["cam2.err"]])
    best = None
    for share, floor in itertools.product(SHARES, FLOORS):
        raw = np.concatenate([flow_raw(d, c, share, floor) for c in ("cam1", "cam2")])
        s = _scale(err, raw)

        def shares(t, s=s, share=share, floor=floor):
            e = np.concatenate([t["cam1.err"], t["cam2.err"]])
            r = np.concatenate([flow_raw(t, c, share, floor) for c in ("cam1", "cam2")])
            return within(e, s * r, 2.0)

        key = (_flatness(err, s * raw) + _scene_spread(big, shares), float(np.median(s * raw)))
        if best is None or key < best[0]:
            best = (key, share, floor, s)
    out = {"flow_share": best[1], "flow_floor": best[2], "flow_scale": best[3]}
    big = [t for t in train if t["range.err"].size >= MIN_POINTS]
    best = None
    for st, floor in itertools.product(SCORE_TERMS, RANGE_FLOORS):
        raw = range_raw(d, st, floor)
        s = _scale(d["range.err"], raw)

        def shares(t, s=s, st=st, floor=floor):
            return within(t["range.err"], s * range_raw(t, st, floor), 2.0)

        key = (_flatness(d["range.err"], s * raw) + _scene_spread(big, shares),
               float(np.median(s * raw)))  # fmt: skip
        if best is None or key < best[0]:
            best = (key, st, floor, s)
    out.update(range_score=best[1], range_floor=best[2], range_scale=best[3])
    return out


def coverage(data: dict, c: dict) -> dict[str, dict[str, float]]:
    """Shares within 1 and 2 sigma per quantity with the constants ``c``."""
    out = {}
    for cam in ("cam1", "cam2"):
        sig = c["flow_scale"] * flow_raw(data, cam, c["flow_share"], c["flow_floor"])
        out[cam] = _cov(data[f"{cam}.err"], sig)
    sig = c["range_scale"] * range_raw(data, c["range_score"], c["range_floor"])
    out["range"] = _cov(data["range.err"], sig)
    return out


def _cov(err, sig):
    return {"n": int(err.size), "within1": within(err, sig, 1.0), "within2": within(err, sig, 2.0)}


def _rendered(dataset: Path, frames: int) -> bool:
    try:
        return len(open_dataset(dataset).frames_done()) >= frames
    except Exception:  # broad: a render not started or half written is simply not there yet
        return False


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m validation.sigma_fit", description=__doc__)
    ap.add_argument("suite")
    ap.add_argument("renders")
    ap.add_argument("--methods", default="default,dense")
    ap.add_argument("--cache", default=None, help="keep each scene's points here (npz)")
    ap.add_argument("--json", default=None, help="write the constants and figures here")
    ap.add_argument("--pairs", type=int, default=None, help="the first N frame pairs per scene")
    ap.add_argument("--cached-only", action="store_true", help="fit on the cached scenes only")
    ap.add_argument("--collect", choices=("train", "test"), default=None,
                    help="only collect this split's points into --cache (no fit)")  # fmt: skip
    args = ap.parse_args(argv)
    suite = load_suite(args.suite)
    neutral = sigma_mod.SigmaModel()
    sigma_mod.MODELS.update({k: neutral for k in sigma_mod.MODELS})  # the raw terms
    report = {}
    presets = args.methods.split(",")
    points: dict[str, dict] = {p: {} for p in presets}
    scenes = sorted(suite.scenes, key=lambda s: s.split != "train")  # train first
    if args.collect:
        scenes = [s for s in scenes if s.split == args.collect]
    for scene in scenes:
        for preset in presets:
            cache = None if args.cache is None else Path(args.cache) / f"{scene.name}.{preset}.npz"
            if cache is not None and cache.exists():
                with np.load(cache) as z:
                    points[preset][scene.name] = {k: z[k] for k in z.files}
                continue
            if args.cached_only or not _rendered(Path(args.renders) / scene.name, suite.frames):
                print(f"sigma_fit: {scene.name}: not collected, left out", file=sys.stderr)
                continue
            print(f"sigma_fit: {preset} {scene.name}", file=sys.stderr, flush=True)
            got = collect(Path(args.renders) / scene.name, preset, args.pairs)
            points[preset][scene.name] = got
            if cache is not None:
                cache.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(cache, **got)
    if args.collect:
        return 0
    for preset in presets:
        per = points[preset]
        split = {s.name: s.split for s in suite.scenes}
        if not any(split[n] == "train" and v for n, v in per.items()):
            print(f"sigma_fit: {preset}: no train scene rendered", file=sys.stderr)
            continue
        train = [v for n, v in per.items() if split[n] == "train" and v]
        c = fit(train)
        entry = {"constants": c, "splits": {}, "scenes": {}}
        for sp in ("train", "test"):
            pts = [v for n, v in per.items() if split[n] == sp and v]
            if pts:
                pooled = {k: np.concatenate([p[k] for p in pts]) for k in pts[0]}
                entry["splits"][sp] = coverage(pooled, c)
        for n, v in per.items():
            if v:
                entry["scenes"][n] = {"split": split[n], **coverage(v, c)}
        report[preset] = entry
        print(json.dumps({preset: {"constants": c, "splits": entry["splits"]}}, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
