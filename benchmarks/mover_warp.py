"""Warp test per object: is the ground truth the flow that brightness constancy sees?

For each frame pair t -> t + 1, camera and object of a dataset, the warp residual
``I_{t+1}(x + f(x)) - I_t(x)`` (bilinear, grey levels x 255) at the object's pixels
(eroded by 2 px, ``gt.flow.valid``, the four pixels around ``x + f_true`` on the same
object at t + 1) for the flow ``f`` of:

* ``zero``: no motion (how much the image changes at all);
* ``truth``: ``gt.flow.dx, dy``;
* ``DIS`` (OpenCV DIS medium) and ``Farneback`` (validation.baselines), dense;

on two image sets: ``camera`` (the images omnivalidate forms: validation.inputs, the
dataset's camera model with its noise) and ``clean`` (the same exposure without noise:
the luminance of the EXR radiance x exposure x gain, clipped to [0, 1]).

``scan``: the true flow plus an offset o (px, -1 to 1 in steps of 0.05, refined by a
parabola through the three lowest) along the radial (then tangential) direction; the o
that minimises the clean residual, ``best_offset_r`` / ``_t``, is how far the image
motion brightness constancy prefers on that object lies from the truth (0 where the
truth is also the best warp; not 0 where the shading does not move with the texture,
or the truth is wrong). ``curv_r`` / ``_t``: the residual's rise 0.25 px either side of
the minimum (grey levels): near 0, that component is not determined by the texture.

The rows ``near_OBJECT`` repeat the above on the object's pixels within 4 px of one of
omniflow's points (defaults): the part of the object the method measures.

At omniflow's points (defaults, and the dense preset with ``--dense``), per object: the
mean radial (dh) and tangential (h dtheta) flow of omniflow, of the truth, of DIS and
of Farneback sampled at the same points, and the camera-image warp residual of the
three flows there.

Usage::

    python benchmarks/mover_warp.py DATASET --pairs 0-2 --out OUT.json [--dense]
        [--objects slider,spinner,ball,ring,poster,room.wall_xn]

Prints one table per camera; writes every figure to OUT.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
from collections import defaultdict

import cv2
import numpy as np

from omniflow.io.dataset import grey_of, open_dataset
from omniflow.pipeline import OmniFlowConfig, estimate
from validation.baselines import dis_flow, farneback_flow
from validation.inputs import CAMERAS, Inputs, camera_model
from validation.sampling import bilinear, sample_truth
from validation.scoring_flow import omniflow_points

OFFSETS = np.round(np.linspace(-1.0, 1.0, 41), 3)


def _pairs(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def clean_grey(ds, k: int, cam: str) -> np.ndarray:
    """Noise-free image at the dataset camera's exposure (linear response assumed)."""
    cm = ds.meta.get("camera") or {}
    g = grey_of(ds.read_frame(k, cam)) * float(cm.get("exposure", 1.0)) * float(cm.get("gain", 1.0))
    return np.clip(np.nan_to_num(g), 0.0, 1.0)


def residual(i0, i1, x, y, dx, dy) -> np.ndarray:
    """``I1(x + dx, y + dy) - I0(x, y)`` in grey levels (x 255)."""
    return 255.0 * (bilinear(i1, x + dx, y + dy) - bilinear(i0, x, y))


def rms(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")


def polar(x, y, dx, dy, centre):
    """(dh, h dtheta) of small image displacements (the radial and tangential parts)."""
    ux, uy = x - centre[0], y - centre[1]
    h = np.hypot(ux, uy)
    return (ux * dx + uy * dy) / h, (ux * dy - uy * dx) / h, ux / h, uy / h


def parabola_min(xs: np.ndarray, ys: np.ndarray) -> tuple[float, float]:
    """Minimum of a sampled curve (parabola through the lowest sample and its neighbours)
    and the parabola's rise 0.25 either side of it."""
    k = int(np.clip(np.argmin(ys), 1, len(ys) - 2))
    a, b, _ = np.polyfit(xs[k - 1 : k + 2], ys[k - 1 : k + 2], 2)
    if a <= 0:
        return float(xs[int(np.argmin(ys))]), 0.0
    return float(-b / (2 * a)), float(a * 0.25**2)


def object_pixels(tr0, tr1, oid: int):
    """Eroded, flow-valid pixels of object ``oid`` whose true next position lies on it."""
    obj0 = np.rint(tr0["gt.object"]).astype(int)
    mask = ((obj0 == oid) & (tr0["gt.valid"] > 0.5)).astype(np.uint8)
    mask = cv2.erode(mask, np.ones((5, 5), np.uint8)) > 0
    mask &= tr0["gt.flow.valid"] > 0.5
    ii, jj = np.nonzero(mask)
    x, y = jj + 0.5, ii + 0.5
    dx = tr0["gt.flow.dx"][ii, jj].astype(np.float64)
    dy = tr0["gt.flow.dy"][ii, jj].astype(np.float64)
    nxt = sample_truth(tr1, x + dx, y + dy, channels=())
    on = nxt["bilinear_ok"] & (
        np.rint(bilinear(tr1["gt.object"], x + dx, y + dy)) == oid
    )  # four corners valid, on one object, and that object is this one
    return ii[on], jj[on]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--pairs", default="0-2")
    ap.add_argument("--out", required=True)
    ap.add_argument("--dense", action="store_true", help="also the dense preset's points")
    ap.add_argument("--objects", default="slider,spinner,ball,ring,poster,room.wall_xn")
    args = ap.parse_args(argv)

    ds = open_dataset(args.dataset)
    names = {v["name"] if isinstance(v, dict) else v: int(k) for k, v in ds.objects.items()}
    wanted = {n: names[n] for n in args.objects.split(",") if n in names}
    inputs = Inputs(ds, camera_model(ds.meta))
    rig = ds.rig
    units = {"cam1": rig.cam1, "cam2": rig.cam2}
    configs = {"ours": OmniFlowConfig()}
    if args.dense:
        configs["ours-dense"] = OmniFlowConfig.dense()
    acc: dict = defaultdict(lambda: defaultdict(list))  # (cam, obj) -> key -> list of arrays

    for t in _pairs(args.pairs):
        tr = {k: {c: ds.read_frame(k, c) for c in CAMERAS} for k in (t, t + 1)}
        u8 = {c: [inputs.u8(k, c) for k in (t, t + 1)] for c in CAMERAS}
        cam_img = {c: [inputs.grey(k, c) for k in (t, t + 1)] for c in CAMERAS}
        clean = {c: [clean_grey(ds, k, c) for k in (t, t + 1)] for c in CAMERAS}
        dense = {c: {"DIS": dis_flow(*u8[c]), "Farneback": farneback_flow(*u8[c])} for c in CAMERAS}
        ours = {
            name: estimate(cam_img["cam1"], cam_img["cam2"], rig, cfg).columns
            for name, cfg in configs.items()
        }
        for cam in CAMERAS:
            c0 = (units[cam].x_c, units[cam].y_c)
            i0c, i1c = cam_img[cam]
            i0n, i1n = clean[cam]
            px, py, _ = omniflow_points(ours["ours"], cam)
            near_pts = np.zeros(i0c.shape, np.uint8)
            ok = np.isfinite(px) & np.isfinite(py)
            near_pts[py[ok].astype(int), px[ok].astype(int)] = 1
            near_pts = cv2.dilate(near_pts, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9)))
            for (oname, oid), near in itertools.product(wanted.items(), ("", "near_")):
                a = acc[(cam, near + oname)]
                ii, jj = object_pixels(tr[t][cam], tr[t + 1][cam], oid)
                if near:  # only the object's pixels within 4 px of one of omniflow's points
                    keep = near_pts[ii, jj] > 0
                    ii, jj = ii[keep], jj[keep]
                if ii.size == 0:
                    continue
                x, y = jj + 0.5, ii + 0.5
                tdx = tr[t][cam]["gt.flow.dx"][ii, jj].astype(np.float64)
                tdy = tr[t][cam]["gt.flow.dy"][ii, jj].astype(np.float64)
                dh, ht, ex, ey = polar(x, y, tdx, tdy, c0)
                a["true_dh"].append(dh)
                a["true_ht"].append(ht)
                flows = {"zero": (0 * tdx, 0 * tdy), "truth": (tdx, tdy)}
                for b, fl in dense[cam].items():
                    flows[b] = (fl[ii, jj, 0].astype(np.float64), fl[ii, jj, 1].astype(np.float64))
                for fname, (fx, fy) in flows.items():
                    a[f"res_camera_{fname}"].append(residual(i0c, i1c, x, y, fx, fy))
                    a[f"res_clean_{fname}"].append(residual(i0n, i1n, x, y, fx, fy))
                    if fname in dense[cam]:
                        bdh, bht, _, _ = polar(x, y, fx, fy, c0)
                        a[f"dense_{fname}_dh"].append(bdh)
                        a[f"dense_{fname}_ht"].append(bht)
                for o in OFFSETS:  # the truth moved by o px radially, then tangentially
                    a[f"scan_r_{o}"].append(residual(i0n, i1n, x, y, tdx + o * ex, tdy + o * ey))
                    a[f"scan_t_{o}"].append(residual(i0n, i1n, x, y, tdx - o * ey, tdy + o * ex))
            for name, cols in ours.items():  # at the points themselves
                px, py, est = omniflow_points(cols, cam)
                st = sample_truth(tr[t][cam], px, py)
                for oname, oid in wanted.items():
                    a = acc[(cam, oname)]
                    on = (
                        st["bilinear_ok"]
                        & (st["gt.valid"] > 0.5)
                        & (np.rint(st["gt.object"]) == oid)
                    )
                    on &= np.isfinite(est["dx"])
                    if not on.any():
                        continue
                    x, y = px[on], py[on]
                    fl = {
                        name: (est["dx"][on], est["dy"][on]),
                        "truth": (st["gt.flow.dx"][on], st["gt.flow.dy"][on]),
                    }
                    for b, f in dense[cam].items():
                        fl[b] = (bilinear(f[..., 0], x, y), bilinear(f[..., 1], x, y))
                    for fname, (fx, fy) in fl.items():
                        pdh, pht, _, _ = polar(x, y, fx, fy, c0)
                        a[f"at_{name}_{fname}_dh"].append(pdh)
                        a[f"at_{name}_{fname}_ht"].append(pht)
                        a[f"at_{name}_res_{fname}"].append(residual(i0c, i1c, x, y, fx, fy))
        print(f"pair {t} done", flush=True)

    report: dict = {}
    for (cam, oname), a in sorted(acc.items()):
        cat = {k: np.concatenate(v) for k, v in a.items()}
        row: dict = {"pixels": int(cat["true_dh"].size)} if "true_dh" in cat else {}
        for k, v in cat.items():
            if k.startswith("res_"):
                row[k] = rms(v)
                row[k.replace("res_", "bias_")] = float(np.nanmean(v))
            elif k.startswith("at_") and "_res_" in k:
                row[k] = rms(v)
            elif not k.startswith("scan_"):
                row[k] = float(np.nanmean(v))
        for comp in ("r", "t"):
            if f"scan_{comp}_0.0" not in cat:
                continue
            curve = np.array([rms(cat[f"scan_{comp}_{o}"]) for o in OFFSETS])
            row[f"scan_{comp}"] = dict(zip(map(float, OFFSETS), map(float, curve), strict=True))
            row[f"best_offset_{comp}"], row[f"curv_{comp}"] = parabola_min(OFFSETS, curve)
        for name in configs:
            key = f"at_{name}_{name}_dh"
            if key in cat:
                row[f"n_{name}"] = int(cat[key].size)
        report[f"{cam}/{oname}"] = row
    with open(args.out, "w") as fh:
        json.dump(report, fh, indent=1)

    for cam in CAMERAS:
        print(f"\n{cam}: RMS warp residual (grey levels, clean | camera images), pixels eroded")
        print("object              px  zero / truth / DIS / Farneback  BC offset r, t (px)"
              "  curvature r | t  true dh  DIS dh  true h dth  DIS h dth")  # fmt: skip
        for oname in [n for o in wanted for n in (o, "near_" + o)]:
            r = report.get(f"{cam}/{oname}")
            if not r or "pixels" not in r:
                continue
            cells = " ".join(
                f"{r[f'res_clean_{f}']:5.2f}|{r[f'res_camera_{f}']:5.2f}"
                for f in ("zero", "truth", "DIS", "Farneback")
            )
            offs = f"{r['best_offset_r']:6.2f} {r['best_offset_t']:6.2f}"
            curv = f"{r['curv_r']:4.2f}|{r['curv_t']:4.2f}"
            means = " ".join(
                f"{r[k]:8.3f}" for k in ("true_dh", "dense_DIS_dh", "true_ht", "dense_DIS_ht")
            )
            print(f"{oname:17s} {r['pixels']:6d} {cells} {offs} {curv} {means}")
        for name in configs:
            print(f"  at {name}'s points: n; mean dh and h dtheta of {name} / truth / DIS /"
                  f" Farneback; RMS residual (camera images) of {name} / truth / DIS")  # fmt: skip
            for oname in wanted:
                r = report.get(f"{cam}/{oname}", {})
                if f"n_{name}" not in r:
                    continue
                p = f"at_{name}_"
                four = (name, "truth", "DIS", "Farneback")
                dh = " ".join(f"{r[p + f + '_dh']:7.3f}" for f in four)
                ht = " ".join(f"{r[p + f + '_ht']:7.3f}" for f in four)
                res = " ".join(f"{r[p + 'res_' + f]:5.2f}" for f in (name, "truth", "DIS"))
                print(f"  {oname:12s} {r[f'n_{name}']:5d}  dh {dh}  ht {ht}  res {res}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
