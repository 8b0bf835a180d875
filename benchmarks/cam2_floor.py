"""Where cam2's flow error comes from, against DIS-medium at the same points (issue 9).

Forms the images exactly as ``omnivalidate`` does (:class:`validation.inputs.Inputs`,
the dataset's camera model with ``--camera`` overrides), runs omniflow and OpenCV
DIS-medium on each frame pair and scores both at omniflow's points of each camera,
split by point class: ``static`` (true displacement below 0.02 px in that camera:
the background of a robot standing still) and ``moving``. Per class it prints the
mean / median EPE of both, their ratio, the rms of the radial (dh) and tangential
(h dtheta) error, and the contribution of the class to the mean EPE over all points.

Oracles (``--oracle``, repeatable):

* ``none``: the pipeline as configured (matching included);
* ``h2``: omniflow's own matched points, with h2 replaced by the true match
  (``gt.stereo.h_other``): the flow step with the true range;
* ``truth``: the flow step on validation's true matches (:func:`validation.variants.true_matches`).

For each run it also prints post-hoc substitutions: the EPE with omniflow's radial
(or tangential) component replaced by the truth, and cam2's EPE predicted as
h2/h1 times cam1's (eq. 14 carries cam1's error into cam2 scaled by h2/h1; the
tangential pixel flow h dtheta scales by the same factor).

    python benchmarks/cam2_floor.py DATASET [--frames 0-2] [--row dense]
        [--set KEY=VALUE ...] [--camera KEY=VALUE ...] [--oracle none|h2|truth ...]
"""

from __future__ import annotations

import argparse
import ast

import numpy as np

from omniflow.io.dataset import open_dataset
from omniflow.matching import Matches
from omniflow.pipeline import OmniFlowConfig, estimate
from validation import baselines as bl
from validation.inputs import Inputs, camera_model
from validation.sampling import sample_truth
from validation.scoring_derived import moving_objects
from validation.scoring_flow import omniflow_points, score_flow
from validation.variants import true_matches

STATIC_PX = 0.02  # true displacement below this (px per frame) counts as static


def frames_arg(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def config_of(row: str, sets: list[str]) -> OmniFlowConfig:
    kw = {}
    for item in sets:
        k, v = item.split("=", 1)
        try:
            kw[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            kw[k] = v
    return OmniFlowConfig.dense(**kw) if row == "dense" else OmniFlowConfig(**kw)


def true_h2_matches(cols: dict, truth1: dict, rig) -> Matches:
    """omniflow's matched cam1 points with the true h2 (where it is defined)."""
    tr = sample_truth(truth1, cols["x"], cols["y"], channels=("gt.stereo.h_other",))
    h2 = tr["gt.stereo.h_other"]
    ok = np.isfinite(h2) & tr["bilinear_ok"]
    return Matches.from_polar(rig, cols["theta"][ok], cols["h1"][ok], h2[ok], n_significant=0)


def collect(ds, inputs, rig, cfg, pairs, oracle):
    """Per camera, concatenated per-point arrays over the pairs."""
    movers = set(moving_objects(ds.meta))
    units = {"cam1": rig.cam1, "cam2": rig.cam2}
    acc = {c: {} for c in units}
    for t in pairs:
        truth = {c: ds.read_frame(t, c) for c in units}
        made = {c: [inputs.frame(k, c, truth[c] if k == t else None) for k in (t, t + 1)]
                for c in units}  # fmt: skip
        grey = {c: [m[1] for m in made[c]] for c in units}
        dis = {c: bl.dense_baseline("DIS-medium", made[c][0][0], made[c][1][0], units[c])
               for c in units}  # fmt: skip
        m = None
        if oracle == "truth":
            m = true_matches(grey["cam1"][0], truth["cam1"], rig, 80.0, band=cfg.band)
        elif oracle == "h2":
            m = true_h2_matches(estimate(grey["cam1"], grey["cam2"], rig, cfg).columns,
                                truth["cam1"], rig)  # fmt: skip
        cols = estimate(grey["cam1"], grey["cam2"], rig, cfg, matches=m).columns
        # one set of points per pair: those scored in both cameras
        x1, y1, e1 = omniflow_points(cols, "cam1")
        x2, y2, e2 = omniflow_points(cols, "cam2")
        tr1 = sample_truth(truth["cam1"], x1, y1, channels=("gt.valid",))
        tr2 = sample_truth(truth["cam2"], x2, y2, channels=("gt.valid",))
        keep = tr1["bilinear_ok"] & tr2["bilinear_ok"] & (tr1["gt.valid"] > 0.5)
        keep &= tr2["gt.valid"] > 0.5
        for k in ("dx", "dy", "dh", "hdtheta"):
            keep &= np.isfinite(e1[k]) & np.isfinite(e2[k])
        k12 = (cols["h2"] / cols["h1"])[keep]
        for cam, x, y, est in (("cam1", x1, y1, e1), ("cam2", x2, y2, e2)):
            x, y = x[keep], y[keep]
            est = {k: v[keep] for k, v in est.items()}
            ours = score_flow(est, x, y, truth[cam])
            base = score_flow(dis[cam].at(x, y), x, y, truth[cam])
            assert ours["epe"].size == x.size == base["epe"].size
            row = {
                "epe": ours["epe"], "err_dh": ours["est_dh"] - ours["gt_dh"],
                "err_t": ours["est_hdtheta"] - ours["gt_hdtheta"],
                "dis_epe": base["epe"], "dis_dh": base["est_dh"] - base["gt_dh"],
                "dis_t": base["est_hdtheta"] - base["gt_hdtheta"],
                "speed": ours["speed"], "k": k12,
                "still": (ours["est_dh"] == 0.0) & (ours["est_hdtheta"] == 0.0),
                "mover": np.isin(np.rint(ours["object"]), list(movers)),
            }  # fmt: skip
            for key, v in row.items():
                acc[cam].setdefault(key, []).append(v)
    return {c: {k: np.concatenate(v) for k, v in a.items()} for c, a in acc.items()}


def report(acc, label: str) -> None:
    rms = lambda v: float(np.sqrt(np.mean(v**2))) if v.size else float("nan")  # noqa: E731
    print(f"== {label}")
    print(" cam class     n    ours mean/med   DIS mean/med  ratio mean/med  share | "
          "rms ours dh/t    rms DIS dh/t   | still")  # fmt: skip
    for cam, a in acc.items():
        n_all = a["epe"].size
        static = a["speed"] < STATIC_PX
        for name, sel in (("all", np.ones(n_all, bool)), ("static", static),
                          ("moving", ~static), ("movers", a["mover"])):  # fmt: skip
            if not sel.any():
                continue
            o, d = a["epe"][sel], a["dis_epe"][sel]
            share = o.sum() / a["epe"].sum()
            print(f" {cam} {name:7s} {sel.sum():6d}  {o.mean():.4f}/{np.median(o):.4f}  "
                  f"{d.mean():.4f}/{np.median(d):.4f}  {o.mean() / d.mean():5.2f}/"
                  f"{np.median(o) / np.median(d):5.2f}  {share:5.2f} | "
                  f"{rms(a['err_dh'][sel]):.4f}/{rms(a['err_t'][sel]):.4f}  "
                  f"{rms(a['dis_dh'][sel]):.4f}/{rms(a['dis_t'][sel]):.4f} | "
                  f"{a['still'][sel].mean():.2f}")  # fmt: skip
    a1, a2 = acc["cam1"], acc["cam2"]
    d2 = a2["dis_epe"]
    pred = a2["k"] * a1["epe"]
    ratio = (a2["epe"].mean() / pred.mean(), np.median(a2["epe"]) / np.median(pred))
    print(f" h2/h1 median {np.median(a2['k']):.3f}; cam2 EPE / (h2/h1 x cam1 EPE): mean "
          f"{ratio[0]:.3f}, median {ratio[1]:.3f}")  # fmt: skip
    for cam, a in acc.items():
        no_r = np.hypot(0.0, a["err_t"])  # radial replaced by the truth
        no_t = np.hypot(a["err_dh"], 0.0)  # tangential replaced by the truth
        d = a["dis_epe"]
        print(f" {cam}: polar EPE {np.hypot(a['err_dh'], a['err_t']).mean():.4f}; true radial -> "
              f"{no_r.mean():.4f}/{np.median(no_r):.4f} ({no_r.mean() / d.mean():.2f}/"
              f"{np.median(no_r) / np.median(d):.2f} x DIS); true tangential -> "
              f"{no_t.mean():.4f}/{np.median(no_t):.4f} ({no_t.mean() / d.mean():.2f}/"
              f"{np.median(no_t) / np.median(d):.2f} x DIS)")  # fmt: skip
    print(
        f" cam2 target 0.5x DIS: mean <= {0.5 * d2.mean():.4f}, median <= {0.5 * np.median(d2):.4f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--frames", default="0-2", type=frames_arg)
    ap.add_argument("--row", choices=("default", "dense"), default="default")
    ap.add_argument("--set", action="append", default=[], help="OmniFlowConfig KEY=VALUE")
    ap.add_argument("--camera", action="append", default=[], help="camera KEY=VALUE")
    ap.add_argument("--oracle", action="append", choices=("none", "h2", "truth"))
    args = ap.parse_args()
    ds = open_dataset(args.dataset)
    cam = camera_model(ds.meta, args.camera)
    auto = not isinstance(ds.meta.get("camera"), dict) and not any(
        c.split("=", 1)[0] == "exposure" for c in args.camera
    )
    inputs = Inputs(ds, cam, auto_exposure=auto)
    cfg = config_of(args.row, args.set)
    for oracle in args.oracle or ["none"]:
        acc = collect(ds, inputs, ds.rig, cfg, args.frames, oracle)
        label = (f"{ds.meta.get('scene', {}).get('name', args.dataset)} row={args.row} "
                 f"set={args.set} camera={args.camera} oracle={oracle}")  # fmt: skip
        report(acc, label)


if __name__ == "__main__":
    main()
