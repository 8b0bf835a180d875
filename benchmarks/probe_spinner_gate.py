"""Probe: which gate lets the coupled linear gain fix the spinner and no static point?

The coupled model with a gain varying linearly across the pool ("L" of
benchmarks/probe_mover_brightness.py: (beta + beta_u u_j + beta_h dh_j) f_j, eq. 14
kept), taken where its F against the plain fit passes 20, brings independent_movers'
spinner within 10 %, but lets through a few static points at the spinner's silhouette
(docs/measurements.md, "Ring, spinner, poster"). This probe runs that probe's pair
solve (omniflow's defaults, its first solve re-solved in numpy with each model), and
at the points omniflow left coupled it replaces omniflow's answer by the refined
coupled L answer where a candidate gate passes:

* ``F``: the F of L's three gain columns against the plain fit (A),
* ``ratio``: RSS_A / RSS_L, the effect size (as ``omniflow.solve.gain.MIN_RESIDUAL_RATIO``),
* ``dof``: n_eff - 7 (L's unknowns, linear flow model), as ``MIN_RESIDUAL_DOF``,
* ``slope``: the larger fitted slope |beta_u|, |beta_h| (over one pool radius),
* ``edge``: the range test drops more than a quarter of the pool's neighbours.

It prints, per object, those statistics at the points whose F passes, every static
point that passes with its error before / after, and, per rule, each mover's mean
flow vector error |mean est - mean true| / |mean true| (issue 9), cam1 / cam2, and the
static objects' mean EPE. Run::

    python benchmarks/probe_spinner_gate.py /work/data/independent_movers \\
        /work/data/approach /work/data/crossing /work/data/default --frames 0,1,2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import probe_mover_brightness as pmb

L_UNKNOWNS = 7  # a, c, u a, u c (linear flow model), beta, beta_u, beta_h


def statistics(p: dict) -> dict[str, np.ndarray]:
    """The candidate gates' statistics at one pair's points."""
    c = p["coupled"]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = c["rss_A"] / c["rss_L"]
    terms = np.abs(c["terms_L"])
    with np.errstate(divide="ignore", invalid="ignore"):  # the slopes against one gain
        slopes_f = (c["rss_C"] - c["rss_L"]) / 2.0 / (c["rss_L"] / (c["n_eff"] - L_UNKNOWNS))
    return {
        "F_S": slopes_f,
        "beta_C": np.abs(c["beta_C"]),
        "F": p["F"]["L"],
        "F_C": p["F"]["C"],
        "ratio": ratio,
        "dof": c["n_eff"] - L_UNKNOWNS,
        "beta": terms[:, 0],
        "slope": terms[:, 1:].max(axis=1),
        "edge": c["edge_share"],
        "coupled": ~c["switched"],
    }


def rules(s: dict, gate: float) -> dict[str, np.ndarray]:
    """Where each candidate rule takes the coupled L answer (only at coupled points)."""
    with np.errstate(invalid="ignore"):
        base = s["coupled"] & (s["F"] > gate)
        out = {f"F>{gate:g}": base}
        for r in (1.2, 1.3, 1.5, 2.0):
            out[f"F>{gate:g} ratio>={r:g}"] = base & (s["ratio"] >= r)
        for dof in (4.0, 10.0, 20.0):
            out[f"F>{gate:g} dof>={dof:g}"] = base & (s["dof"] >= dof)
        for g in (0.01, 0.02, 0.03):
            out[f"F>{gate:g} slope>={g:g}"] = base & (s["slope"] >= g)
        out[f"F>{gate:g} not edge"] = base & ~(s["edge"] > 0.25)
        # as built (omniflow.solve.gain, brightness_model "linear"): the residual degrees of
        # freedom and a least term, MIN_RESIDUAL_DOF and MIN_CHANGE
        term = np.maximum(s["beta"], s["slope"])
        lin = base & (s["dof"] >= 4.0) & (term >= 0.002)
        out[f"F>{gate:g} dof>=4 term>=0.002"] = lin
        # and one gain kept where it passes and the slopes' F against it does not
        one = (s["F_C"] > gate) & (s["beta_C"] >= 0.002) & ~(s["F_S"] > gate)
        out["as built"] = lin & ~one
    return out


def score(est, true, obj, movers, names) -> str:
    """Each mover's issue-9 error, cam1 / cam2 (%), and the static mean EPE."""
    cells = []
    for o in movers:
        m = obj == o
        if not m.any():
            continue
        err = [np.hypot(*(est[c : c + 2, m].mean(axis=1) - true[c : c + 2, m].mean(axis=1)))
               / np.hypot(*true[c : c + 2, m].mean(axis=1)) for c in (0, 2)]  # fmt: skip
        tg = est[1, m].mean() / true[1, m].mean()
        cells.append(f"{names.get(o, o)[:8]:>8s} {100 * err[0]:5.1f}/{100 * err[1]:5.1f} "
                     f"(t {tg:.2f})")  # fmt: skip
    st = ~np.isin(obj, list(movers))
    e1, e2 = np.hypot(*(est[:2] - true[:2])), np.hypot(*(est[2:] - true[2:]))
    cells.append(f"static {e1[st].mean():.5f}/{e2[st].mean():.5f}")
    return "  ".join(cells)


def report(ds, directory, parts, movers, gate) -> None:
    names = dict(ds.objects)
    cat = lambda get: np.concatenate([get(p) for p in parts], axis=-1)  # noqa: E731
    v = lambda p: p["valid"]  # noqa: E731
    obj = cat(lambda p: p["obj"][v(p)])
    true = cat(lambda p: p["truth"][:, v(p)])
    stats = {k: cat(lambda p, k=k: statistics(p)[k][v(p)]) for k in statistics(parts[0])}
    omni = cat(lambda p: p["est"]["omniflow"][:, v(p)])
    lin = cat(lambda p: p["est"]["L"][:, v(p)])
    pair = cat(lambda p: np.full(v(p).sum(), p["pair"]))
    movers = sorted(movers)
    print(f"== {directory}: {obj.size} points, gate F > {gate:g}")
    e_o = np.hypot(*(omni[:2] - true[:2])), np.hypot(*(omni[2:] - true[2:]))
    e_l = np.hypot(*(lin[:2] - true[:2])), np.hypot(*(lin[2:] - true[2:]))
    with np.errstate(invalid="ignore"):
        passing = stats["coupled"] & (stats["F"] > gate)
    print(
        "-- points whose F passes (coupled only): n / of; min-median-max of ratio, dof, "
        "slope, |beta|, edge share; mean EPE cam1 omniflow -> L"
    )
    st = ~np.isin(obj, movers)
    for label, m in [*((names.get(o, str(o)), obj == o) for o in movers), ("static", st)]:
        q = m & passing
        if not m.any():
            continue
        line = f"   {label[:10]:10s} {q.sum():4d} / {m.sum():5d}"
        if q.any():
            for k in ("ratio", "dof", "slope", "beta", "edge"):
                x = stats[k][q]
                line += f"  {k} {x.min():.3g}-{np.median(x):.3g}-{x.max():.3g}"
            line += f"  EPE {e_o[0][q].mean():.3f} -> {e_l[0][q].mean():.3f}"
        print(line)
    print(
        "-- static points passing: pair, object, F, ratio, dof, slope, |beta|, edge, "
        "EPE cam1 / cam2 omniflow -> L"
    )
    for i in np.flatnonzero(st & passing):
        print(f"   {pair[i]} {names.get(obj[i], obj[i])[:14]:14s} F {stats['F'][i]:6.1f} "
              f"ratio {stats['ratio'][i]:5.2f} dof {stats['dof'][i]:5.1f} "
              f"slope {stats['slope'][i]:.3f} beta {stats['beta'][i]:.4f} "
              f"edge {stats['edge'][i]:.2f}  {e_o[0][i]:.3f}/{e_o[1][i]:.3f} -> "
              f"{e_l[0][i]:.3f}/{e_l[1][i]:.3f}")  # fmt: skip
    print("-- issue 9 % cam1 / cam2 (t: cam1 tangential mean est / true), static mean EPE")
    print(f"   {'omniflow':28s} {score(omni, true, obj, movers, names)}")
    for label, m in rules(stats, gate).items():
        est = np.where(m[None] & np.isfinite(lin).all(axis=0)[None], lin, omni)
        print(f"   {label:28s} {score(est, true, obj, movers, names)}  ({m.sum()} points)")
    print(flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--frames", default="0,1,2", help="first frames of the pairs")
    parser.add_argument("--gate", type=float, default=20.0, help="the F gate of L against A")
    args = parser.parse_args()

    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from validation.inputs import Inputs, camera_model
    from validation.scoring_derived import moving_objects

    config = OmniFlowConfig()
    # the brightness probe's own settings (its gates are not used here)
    args.gates, args.dec_gates, args.edge_gate, args.edge_share = [20.0], [20.0, 10.0], 10.0, 0.25
    seen: dict = {}
    pmb.capture(seen)
    for directory in args.datasets:
        ds = open_dataset(directory)
        camera = camera_model(ds.meta)
        inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
        args.movers = set(moving_objects(ds.meta))
        parts = []
        for t in (int(v) for v in args.frames.split(",")):
            parts.append(pmb.run_pair(ds, inputs, t, config, seen, args))
            parts[-1]["pair"] = t
        report(ds, directory, parts, args.movers, args.gate)


if __name__ == "__main__":
    main()
