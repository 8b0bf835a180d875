"""Gains and endpoint errors of omniflow's flow step on rendered datasets, against DIS.

Used for the "omniflow accuracy" tables of docs/measurements.md. Each frame's
Rec. 709 luminance is scaled as validation does (99.5th percentile of frame 0's
valid pixels to 255), Gaussian noise of ``noise`` times the mean valid grey
is added and the result rounded to 8 bits (a stand-in for the camera model of
the image-formation issue). Reported per configuration: the radial and
tangential gain (least-squares slope through the origin of estimated against
true dh_1 and h_1 dtheta), mean / median endpoint error of both cameras, DIS
medium's at the same points, points per frame (share of valid pixels), the
stereo outlier rate (|h2 - gt.stereo.h_other| > 1 px) and, per object id,
points and the relative error of the object's mean flow.

    python benchmarks/omniflow_accuracy.py DATASET PAIRS match|truth [CONFIG ...]

CONFIG: ``key=value;key=value`` fields of OmniFlowConfig ("" is the default).
"""

import ast
import sys
import time

import numpy as np

from omniflow.conventions import LUMA_WEIGHTS
from omniflow.pipeline import OmniFlowConfig, estimate
from omnisim.dataset import open_dataset
from validation.baselines import DenseFlow, dis_flow
from validation.runner import true_matches
from validation.sampling import sample_truth

CH = (
    "gt.valid",
    "gt.object",
    "gt.flow.valid",
    "gt.flow.dx",
    "gt.flow.dy",
    "gt.flow.dh",
    "gt.flow.hdtheta",
    "gt.r",
    "gt.stereo.valid",
    "gt.stereo.h_other",
)

_cache = {}


def load(path, noise, seed=0):
    key = (path, noise, seed)
    if key in _cache:
        return _cache[key]
    ds = open_dataset(path)
    rig = ds.rig
    n = ds.frame_count
    import os

    while n > 0 and not os.path.exists(f"{path}/frames/{n - 1:06d}/cam2.flo"):
        n -= 1
    wr, wg, wb = LUMA_WEIGHTS
    raw = {c: [] for c in ("cam1", "cam2")}
    truth = {c: [] for c in ("cam1", "cam2")}
    for k in range(n):
        for c in ("cam1", "cam2"):
            fr = ds.read_frame(k, c)
            raw[c].append((wr * fr["R"] + wg * fr["G"] + wb * fr["B"]).astype(np.float64))
            truth[c].append({ch: fr[ch] for ch in CH if ch in fr})
    v = truth["cam1"][0]["gt.valid"] > 0.5
    scale = 255.0 / np.percentile(raw["cam1"][0][v], 99.5)
    rng = np.random.default_rng(seed)
    imgs = {}
    for c in raw:
        out = []
        for im in raw[c]:
            g = im * scale
            if noise > 0:
                g = g + rng.normal(0, noise * g[truth[c][0]["gt.valid"] > 0.5].mean(), g.shape)
            out.append(np.clip(np.round(g), 0, 255).astype(np.uint8))
        imgs[c] = out
    _cache[key] = (rig, imgs, truth, n)
    return _cache[key]


def gain(est, true):
    ok = np.isfinite(est) & np.isfinite(true)
    return float(np.sum(est[ok] * true[ok]) / np.sum(true[ok] ** 2))


def score(path, cfg, noise=0.01, truth_matches=False, pairs=None, seed=0, dis=True):
    rig, imgs, truth, n = load(path, noise, seed)
    pairs = range(n - 1) if pairs is None else pairs
    acc = {
        k: []
        for k in (
            "er",
            "tr",
            "et",
            "tt",
            "e1",
            "e2",
            "d1",
            "d2",
            "r1d",
            "r2d",
            "obj",
            "ex",
            "ey",
            "tx",
            "ty",
        )
    }
    npts, times = [], []
    for t in pairs:
        f1 = [im.astype(np.float32) / 255 for im in imgs["cam1"]]
        f2 = [im.astype(np.float32) / 255 for im in imgs["cam2"]]
        m = true_matches(imgs["cam1"][t], truth["cam1"][t], rig) if truth_matches else None
        t0 = time.perf_counter()
        res = estimate(f1, f2, rig, cfg, t=t, matches=m)
        times.append(time.perf_counter() - t0)
        c = res.columns
        tr1 = sample_truth(truth["cam1"][t], c["x"], c["y"], channels=CH[:8])
        tr2 = sample_truth(truth["cam2"][t], c["x2"], c["y2"], channels=CH[:8])
        st = sample_truth(
            truth["cam1"][t],
            c["x"],
            c["y"],
            channels=("gt.valid", "gt.object", "gt.stereo.valid", "gt.stereo.h_other"),
        )
        acc.setdefault("out", []).append(~(np.abs(c["h2"] - st["gt.stereo.h_other"]) <= 1.0))
        ok = (
            (tr1["gt.flow.valid"] > 0.5)
            & np.isfinite(tr1["gt.flow.dx"])
            & (tr2["gt.flow.valid"] > 0.5)
            & np.isfinite(tr2["gt.flow.dx"])
        )
        npts.append(int(ok.sum()))
        acc["er"].append(c["dh1_dt"][ok])
        acc["tr"].append(tr1["gt.flow.dh"][ok])
        acc["obj"].append(np.rint(tr1["gt.object"][ok]))
        acc["ex"].append(c["dx"][ok])
        acc["ey"].append(c["dy"][ok])
        acc["tx"].append(tr1["gt.flow.dx"][ok])
        acc["ty"].append(tr1["gt.flow.dy"][ok])
        acc["et"].append((c["h1"] * c["dtheta_dt"])[ok])
        acc["tt"].append(tr1["gt.flow.hdtheta"][ok])
        acc["e1"].append(np.hypot(c["dx"] - tr1["gt.flow.dx"], c["dy"] - tr1["gt.flow.dy"])[ok])
        acc["e2"].append(np.hypot(c["dx2"] - tr2["gt.flow.dx"], c["dy2"] - tr2["gt.flow.dy"])[ok])
        if dis:
            for cam, xs, ys, tr, key in (
                ("cam1", c["x"], c["y"], tr1, "d1"),
                ("cam2", c["x2"], c["y2"], tr2, "d2"),
            ):
                fl = DenseFlow(dis_flow(imgs[cam][t], imgs[cam][t + 1]), getattr(rig, cam))
                a = fl.at(xs[ok], ys[ok])
                acc[key].append(
                    np.hypot(a["dx"] - tr["gt.flow.dx"][ok], a["dy"] - tr["gt.flow.dy"][ok])
                )
        valid = int((truth["cam1"][t]["gt.valid"] > 0.5).sum())
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in acc.items() if k != "out"}
    out = dict(
        gain_r=gain(cat["er"], cat["tr"]),
        gain_t=gain(cat["et"], cat["tt"]),
        e1_mean=float(np.mean(cat["e1"])),
        e1_med=float(np.median(cat["e1"])),
        e2_mean=float(np.mean(cat["e2"])),
        e2_med=float(np.median(cat["e2"])),
        pts=float(np.mean(npts)),
        dens=float(np.mean(npts)) / valid,
        sec=float(np.median(times)),
    )
    objs = {}
    for o in np.unique(cat["obj"]):
        sel = cat["obj"] == o
        mt = np.array([cat["tx"][sel].mean(), cat["ty"][sel].mean()])
        me = np.array([cat["ex"][sel].mean(), cat["ey"][sel].mean()])
        objs[int(o)] = (
            int(sel.sum() / len(npts)),
            float(np.linalg.norm(me - mt) / max(np.linalg.norm(mt), 1e-9)),
        )
    out["objs"] = objs
    out["outl"] = float(np.mean(np.concatenate(acc["out"])))
    if dis:
        out.update(
            d1_mean=float(np.mean(cat["d1"])),
            d1_med=float(np.median(cat["d1"])),
            d2_mean=float(np.mean(cat["d2"])),
            d2_med=float(np.median(cat["d2"])),
        )
    return out


def fmt(name, o):
    s = f"{name:34s} gR {o['gain_r']:.3f} gT {o['gain_t']:.3f} | c1 {o['e1_mean']:.3f}/{o['e1_med']:.3f} c2 {o['e2_mean']:.3f}/{o['e2_med']:.3f}"  # noqa: E501
    if "d1_mean" in o:
        s += f" | DIS c1 {o['d1_mean']:.3f}/{o['d1_med']:.3f} c2 {o['d2_mean']:.3f}/{o['d2_med']:.3f}"  # noqa: E501
    s += f" | pts {o['pts']:.0f} ({100 * o['dens']:.2f}%) {o['sec']:.2f}s st.out {100 * o['outl']:.1f}%"  # noqa: E501
    s += " | obj " + " ".join(f"{k}:{n}/{e:.2f}" for k, (n, e) in o["objs"].items())
    return s


if __name__ == "__main__":
    import ast
    import sys

    data, pairs, mode = sys.argv[1], [int(p) for p in sys.argv[2].split(",")], sys.argv[3]
    for spec in sys.argv[4:] or [""]:
        kw = {}
        for item in filter(None, spec.split(";")):
            k, v = item.split("=", 1)
            kw[k] = ast.literal_eval(v)
        res = score(data, OmniFlowConfig(**kw), 0.01, mode == "truth", pairs)
        print(("T " if mode == "truth" else "M ") + fmt(spec or "default", res), flush=True)
