"""Pooling that respects objects: each pooling knob's effect on the movers and the static scene.

For every dataset and every variant (``NAME:knob=value;knob=value``, no knobs
= the default OmniFlowConfig; a ``truth+`` prefix runs the flow step on the
true stereo matches), scores omniflow with :func:`validation.runner.run_validation`
(the same figures as ``omnivalidate --variants default``) and prints, per
camera, the mean EPE and the radial gain over all points and, per moving
object, the scored points and the error of its mean flow against its mean
true image motion, |mean est - mean true| / |mean true| on the (radial,
tangential) flow vector. With ``--mixing``, also the share of the pool weight
that each mover's matched points draw from other objects (object ids of the
truth at the points; pools as the default solver builds them); with
``--outline``, each mover's radial flow at its matched points within 3 px of its
outline and inside (first variant); with ``--boundary BAND_MEAN``, the
closed-form motion boundary of tests/omniflow/test_pooling.py instead of (or
before) the datasets; with ``--table``, a Markdown row per dataset and variant
(density, EPE mean/median per camera and its ratio to DIS-medium at the same points,
radial gain, time-to-contact error, each mover's error). Run from the repository root
(it imports tests.helpers)::

    PYTHONPATH=$PWD python3 benchmarks/bench_pooling.py runs/crossing/dataset \\
        runs/independent_movers/dataset default: k96:pooling.pool_k=96 \\
        range3:pooling.pool_range_tol=0.03
"""

from __future__ import annotations

import argparse
import ast
import math
import warnings

import numpy as np


def parse_variant(spec: str):
    """``NAME:k=v;k=v`` -> (name, OmniFlowConfig or TrueMatches); a group's knob by its
    dotted name (``grid:pooling.pool_grid=0.125``)."""
    from omniflow.config import OmniFlowConfig
    from validation.variants import TrueMatches

    name, _, body = spec.partition(":")
    knobs = {}
    for item in filter(None, body.split(";")):
        key, _, value = item.partition("=")
        try:
            knobs[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            knobs[key] = value
    config = OmniFlowConfig().with_settings(knobs)
    return name, TrueMatches(config) if name.startswith("truth+") else config


def mover_rows(summary: dict) -> list[str]:
    """One line per method and camera, one per mover."""
    movers = [summary["dataset"]["objects"][str(i)] for i in summary["dataset"]["moving_objects"]]
    lines = []
    for m in summary["methods"]:
        head = []
        for cam in ("cam1", "cam2"):
            a = m["flow"][cam]["all"]
            gain = a["radial"]["gain"]
            head.append(f"{cam} n={a['n']} EPE mean {a['epe']['mean']:.4f} radial gain "
                        f"{float('nan') if gain is None else gain:.3f}")  # fmt: skip
        lines.append(f"{summary['dataset']['scene']:18s} {m['name']:12s} " + " | ".join(head))
        for name in movers:
            cells = []
            for cam in ("cam1", "cam2"):
                o = m["flow"][cam]["objects"][name]
                if not o["n"]:
                    cells.append(f"{cam} n=0")
                    continue
                re_, rt = o["radial"]["mean_est"], o["radial"]["mean_true"]
                te, tt = o["tangential"]["mean_est"], o["tangential"]["mean_true"]
                err = math.hypot(re_ - rt, te - tt) / max(math.hypot(rt, tt), 1e-12)
                cells.append(f"{cam} n={o['n']} mean flow (rad, tan) {re_:+.3f}, {te:+.3f} "
                             f"true {rt:+.3f}, {tt:+.3f} error {100 * err:.1f} %")  # fmt: skip
            lines.append(f"    {name:10s} " + " | ".join(cells))
    return lines


def table_rows(summary: dict) -> list[str]:
    """Markdown rows per method: density, EPE mean/median per camera and their ratio to
    DIS-medium at the same points, radial gain, time to contact, each mover's error."""
    scene = summary["dataset"]["scene"]
    movers = [summary["dataset"]["objects"][str(i)] for i in summary["dataset"]["moving_objects"]]
    rows = []
    for m in summary["methods"]:
        if m["kind"] != "omniflow":
            continue
        cells = []
        for cam in ("cam1", "cam2"):
            e = m["flow"][cam]["all"]["epe"]
            d = (m.get("baselines_at_same_points") or {}).get("DIS-medium", {}).get(cam)
            cells.append(f"{e['mean']:.3f}/{e['median']:.3f}")
            cells.append(f"{e['mean'] / d['mean']:.2f}/{e['median'] / d['median']:.2f}"
                         if d else "-")  # fmt: skip
        dens = m["flow"]["cam1"]["density"]
        gains = "/".join(f"{m['flow'][c]['all']['radial']['gain']:.2f}" for c in ("cam1", "cam2"))
        errs = []
        for name in movers:
            o = m["flow"]["cam1"]["objects"][name]
            if not o["n"]:
                errs.append(f"{name} n=0")
                continue
            re_, rt = o["radial"]["mean_est"], o["radial"]["mean_true"]
            te, tt = o["tangential"]["mean_est"], o["tangential"]["mean_true"]
            err = math.hypot(re_ - rt, te - tt) / max(math.hypot(rt, tt), 1e-12)
            errs.append(f"{name} {100 * err:.1f} (n {o['n']})")
        ttc = (m["derived"].get("ttc_relative_error") or {}).get("median")
        ttc_cell = "-" if ttc is None else f"{ttc:.3f}"
        outl = m["stereo"]["all"]["outliers"]
        rows.append(f"| {scene} | {m['name']} | {100 * dens['of_valid_pixels']:.2f} | "
                    f"{dens['points_per_frame']:.0f} | " + " | ".join(cells) + f" | {gains} | "
                    + ("; ".join(errs) or "-") + " | "
                    + f"{ttc_cell} | {100 * outl:.1f} |")  # fmt: skip
    return rows


TABLE_HEAD = (
    "| scene | variant | dens % | pts/fr | cam1 EPE mean/med | ratio DIS | cam2 EPE mean/med "
    "| ratio DIS | gain r cam1/cam2 | movers: mean-flow error % (cam1) | TTC med rel "
    "| stereo outliers % |\n" + "|---" * 12 + "|"
)


def mixing(dataset: str) -> list[str]:
    """Share of the default pools' weight that each mover's points draw from other objects."""
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from omniflow.solve.pooled import neighbourhoods
    from validation.inputs import Inputs, camera_model
    from validation.scoring_derived import moving_objects

    ds = open_dataset(dataset)
    inputs = Inputs(ds, camera_model(ds.meta))
    config = OmniFlowConfig()
    radius = ds.rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    movers = {int(i): ds.objects[int(i)] for i in moving_objects(ds.meta)}
    share: dict[int, list[float]] = {i: [] for i in movers}
    for t in range(ds.frame_count - 1):
        f1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
        f2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
        res = estimate(f1, f2, ds.rig, config, t=0)
        obj_map = ds.read_frame(t, "cam1")["gt.object"]
        iy = np.clip(res["y"].astype(int), 0, obj_map.shape[0] - 1)
        ix = np.clip(res["x"].astype(int), 0, obj_map.shape[1] - 1)
        obj = obj_map[iy, ix].astype(int)
        idx, w = neighbourhoods(res["x"], res["y"], k=config.pooling.pool_k, radius=radius,
                                r=res["r"], range_tol=config.pooling.pool_range_tol)  # fmt: skip
        other = np.append(obj, -1)[idx] != obj[:, None]
        frac = (w * other).sum(axis=1) / w.sum(axis=1)
        for i in movers:
            share[i] += list(frac[obj == i])
    return [f"    {movers[i]:10s} {len(v)} points, pool weight from other objects: mean "
            f"{np.mean(v) if v else float('nan'):.3f}" for i, v in share.items()]  # fmt: skip


def boundary(variants: list, band_mean: float, share: float = 0.1) -> list[str]:
    """The closed-form motion boundary of tests/omniflow/test_pooling.py, per variant."""
    from omniflow.pipeline import estimate
    from omniflow.solve.pooled import neighbourhoods
    from tests.helpers.scenes import band_scene, frames, paper_rig, sparse_true_matches

    rig = paper_rig(256)
    scene = band_scene(rig, yaw=0.01, band_mean=band_mean)
    f1, f2 = frames(scene, 2)
    m, gt = sparse_true_matches(scene, share)  # true matches at this share of the pixels
    lines = [f"band mean {band_mean}: variant | band mean flow / true | band points whose "
             "pool never reaches the wall | wall mean EPE"]  # fmt: skip
    for name, config in variants:
        res = estimate(f1, f2, rig, config, matches=m)
        iy, ix = res["y"].astype(int), res["x"].astype(int)
        obj = gt["gt.object"][iy, ix]
        true_dh, true_tan = gt["gt.flow.dh"][iy, ix], gt["gt.flow.hdtheta"][iy, ix]
        est_tan = res["h1"] * res["dtheta_dt"]
        idx, _ = neighbourhoods(
            res["x"], res["y"], k=config.pooling.pool_k, radius=rig.cam1.r_m / 8.0
        )
        crosses = ((np.append(obj, -1)[idx] != obj[:, None]) & (idx < obj.size)).any(axis=1)
        band, inner = obj == 2, (obj == 2) & ~crosses
        epe = np.hypot(res["dh1_dt"] - true_dh, est_tan - true_tan)
        lines.append(f"{name:12s} {est_tan[band].mean() / true_tan[band].mean():.3f} | "
                     f"{est_tan[inner].mean() / true_tan[inner].mean():.3f} | "
                     f"{epe[obj == 1].mean():.4f}")  # fmt: skip
    return lines


def outline(dataset: str, config, within: float = 3.0) -> list[str]:
    """Each mover's radial flow (est / true means) at matched points near its outline and inside."""
    from scipy.ndimage import distance_transform_edt

    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from validation.inputs import Inputs, camera_model
    from validation.scoring_derived import moving_objects

    ds = open_dataset(dataset)
    inputs = Inputs(ds, camera_model(ds.meta))
    acc: dict[int, list] = {int(i): [] for i in moving_objects(ds.meta)}
    for t in range(ds.frame_count - 1):
        f1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
        f2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
        res = estimate(f1, f2, ds.rig, config)
        ch = ds.read_frame(t, "cam1")
        iy = np.clip(res["y"].astype(int), 0, ch["gt.object"].shape[0] - 1)
        ix = np.clip(res["x"].astype(int), 0, ch["gt.object"].shape[1] - 1)
        obj = ch["gt.object"][iy, ix].astype(int)
        for i in acc:
            dist = distance_transform_edt(ch["gt.object"] == i)[iy, ix]
            sel = obj == i
            h2_err = np.abs(res["h2"] - ch["gt.stereo.h_other"][iy, ix])
            cols = (dist, res["dh1_dt"], ch["gt.flow.dh"][iy, ix], h2_err)
            acc[i] += list(zip(*(c[sel] for c in cols), strict=True))
    lines = []
    for i, rows in acc.items():
        if not rows:
            lines.append(f"    {ds.objects[i]:10s} no points")
            continue
        d, est, true, h2err = (np.array(c) for c in zip(*rows, strict=True))
        near = d <= within
        cells = [f"{lab} {sel.sum()} points radial est {est[sel].mean():+.3f} true "
                 f"{true[sel].mean():+.3f}" for lab, sel in (("near", near), ("inside", ~near))
                 if sel.any()]  # fmt: skip
        lines.append(f"    {ds.objects[i]:10s} (outline = within {within} px) " + "; ".join(cells)
                     + f"; matched h2 error median {np.median(h2err):.2f} px")  # fmt: skip
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", help="dataset directories, then the variants")
    parser.add_argument("--mixing", action="store_true", help="also the pools' mixing shares")
    parser.add_argument("--outline", action="store_true",
                        help="each mover's radial flow near its outline and inside")  # fmt: skip
    parser.add_argument("--boundary", type=float, metavar="BAND_MEAN", action="append",
                        help="the closed-form motion boundary, this band brightness")  # fmt: skip
    parser.add_argument("--share", type=float, default=0.1,
                        help="--boundary: share of the pixels with a true match (0.1)")  # fmt: skip
    parser.add_argument("--table", action="store_true",
                        help="a Markdown table instead (density, EPE and its ratio to "
                             "DIS-medium at the same points, gain, TTC, movers)")  # fmt: skip
    args = parser.parse_args()
    datasets = [a for a in args.datasets if ":" not in a]
    variants = [parse_variant(a) for a in args.datasets if ":" in a] or [parse_variant("default:")]
    from omniflow.io.jsonio import jsonable
    from validation.runner import run_validation
    from validation.summary import summarize

    warnings.simplefilter("ignore")
    for mean in args.boundary or []:
        plain = [(n, c.config if hasattr(c, "percentile") else c) for n, c in variants]
        print("\n".join(boundary(plain, mean, args.share)), flush=True)
    if args.table:
        print(TABLE_HEAD, flush=True)
    for ds in datasets:
        res = run_validation(ds, variants=variants, progress=False,
                             baselines=["DIS-medium"] if args.table else [])  # fmt: skip
        rows = table_rows if args.table else mover_rows
        print("\n".join(rows(jsonable(summarize(res)))), flush=True)
        if args.mixing:
            print("\n".join(mixing(ds)), flush=True)
        if args.outline:
            print("\n".join(outline(ds, variants[0][1])), flush=True)


if __name__ == "__main__":
    main()
