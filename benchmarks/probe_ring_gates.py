"""Which gate of ``decouple_gain_tol``'s test stops a mover's points, and what other rules
would switch (docs/measurements.md, "The ring's unswitched points (stop 22, helper ring)").

For each dataset and pair (t, t + 1), t in ``--frames``: :func:`omniflow.pipeline.estimate`
at the defaults with ``decouple_gain_tol`` None (the answer without the test) and at the
defaults with the gates of :mod:`omniflow.solve.gain` opened (``MIN_RESIDUAL_DOF`` just above 0,
``MIN_RESIDUAL_RATIO`` 1), its linear-gain fits taken from
:func:`omniflow.solve.decoupled.chained` at every point: F_U, the residual degrees of freedom
n_eff - 6, the ratio RSS_coupled / RSS_decoupled = 1 + F_U / (n_eff - 6), the share of the
pool's neighbours the range test drops (``EDGE_SHARE``), and the decoupled + linear-gain
answer. A rule is a set of switched points; its flow is that answer there and the answer
without the test elsewhere (the built defaults reproduced: ring 31.9 / 2.9 %).

Prints (1) the ``--object``'s points (ring) with their statistics and the gates that stop
them, (2) the static points with RSS ratio >= 2 and n_eff - 6 >= 4 that the built F_U gate
stops (their cam1 EPE without -> with the answer), (3) per rule, the points switched on
objects that do not move and issue 9's mean-flow error |mean est - mean true| / |mean true|
of every mover, cam1 / cam2, % (and the point-weighted static mean EPE, every point with
truth on a static object, px)::

    PYTHONPATH=$PWD python benchmarks/probe_ring_gates.py /work/data/independent_movers \\
        /work/data/approach /work/data/crossing /work/data/default /work/data/low_texture

and the 256-px calibration renders (three frames) with ``--frames 0,1``.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import f as f_dist

import omniflow.solve.decoupled as decoupled_mod
import omniflow.solve.gain as gain_mod
from omniflow.config import OmniFlowConfig
from omniflow.io.dataset import open_dataset
from omniflow.pipeline import estimate
from validation.inputs import Inputs, camera_model
from validation.sampling import sample_truth
from validation.scoring_derived import moving_objects


def capture(path: str, frames: list[int]) -> list[dict]:
    """One dict of per-point arrays per pair (see the module's docstring)."""
    seen = {}
    chained, linear_gain = decoupled_mod.chained, decoupled_mod.decoupled_linear_gain

    def spy(fit, tol):
        seen["fit"] = dict(fit)
        return chained(fit, tol)

    def spy_pools(*a, **kw):
        seen["idx"], seen["w"] = a[5], a[6]
        return linear_gain(*a, **kw)

    ds = open_dataset(path)
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    movers = moving_objects(ds.meta)
    gates = gain_mod.MIN_RESIDUAL_DOF, gain_mod.MIN_RESIDUAL_RATIO
    out = []
    for t in frames:
        g1 = [inputs.grey(j, "cam1") for j in (t, t + 1)]
        g2 = [inputs.grey(j, "cam2") for j in (t, t + 1)]
        off = estimate(g1, g2, ds.rig, OmniFlowConfig(decouple_gain_tol=None)).columns
        decoupled_mod.chained, decoupled_mod.decoupled_linear_gain = spy, spy_pools
        gain_mod.MIN_RESIDUAL_DOF, gain_mod.MIN_RESIDUAL_RATIO = 1e-12, 1.0  # F_U alone
        try:
            estimate(g1, g2, ds.rig, OmniFlowConfig())
        finally:
            decoupled_mod.chained, decoupled_mod.decoupled_linear_gain = chained, linear_gain
            gain_mod.MIN_RESIDUAL_DOF, gain_mod.MIN_RESIDUAL_RATIO = gates
        fit, idx, w = seen["fit"], seen["idx"], seen["w"]
        n = fit["gain_F"].size
        tr = [sample_truth(ds.read_frame(t, c), off[x][:n], off[y][:n])
              for c, x, y in (("cam1", "x", "y"), ("cam2", "x2", "y2"))]  # fmt: skip
        obj = np.rint(tr[0]["gt.object"]).astype(int)
        within, kept = (idx < n).sum(axis=1), (w > 0).sum(axis=1)
        with np.errstate(all="ignore"):
            dof = 2.0 * w.sum(axis=1) ** 2 / (w * w).sum(axis=1) - 6.0
            d = dict(
                scene=ds.dir.name, t=t, idx=idx, w=w, F=fit["gain_F"], dof=dof,
                ratio=1.0 + fit["gain_F"] / dof, edge=fit["gain_edge"],
                share=(within - kept) / within, mover=np.isin(obj, movers),
                name=np.array([ds.objects.get(int(o), str(o)) for o in obj]),
                x=off["x"][:n], y=off["y"][:n], h=(off["h1"][:n], off["h2"][:n]),
                off=(off["dh1_dt"][:n], off["dh2_dt"][:n], off["dtheta_dt"][:n]),
                gain=(fit["gain_a1"], fit["gain_a2"], fit["gain_b"]),
                truth=[(r["gt.flow.dh"], r["gt.flow.hdtheta"]) for r in tr],
            )  # fmt: skip
        d["fin"] = np.isfinite(sum(d["gain"]))
        out.append(d)
    return out


def switched(d: dict, edge_gate: float, gate: float, ratio: float = 2.0) -> np.ndarray:
    """The test as built (``MIN_RESIDUAL_DOF`` 4), F_U above ``edge_gate`` on range-edge
    pools and ``gate`` elsewhere, RSS_coupled / RSS_decoupled at least ``ratio``."""
    with np.errstate(invalid="ignore"):
        f_gate = np.where(d["edge"], edge_gate, gate)
        return d["fin"] & (d["dof"] >= 4.0) & (d["ratio"] >= ratio) & (d["F"] > f_gate)


def after(pairs: list[dict], rule, radius: float = 8.0, ratio: float = 1.0) -> list:
    """``rule``, and where the previous pair switched a point within ``radius`` px the
    test's answer whatever F_U (RSS ratio at least ``ratio``): consistency over pairs."""
    masks, prev = [], None
    for d in pairs:
        m = rule(d)
        if prev is not None and prev[2].any():
            tree = cKDTree(np.c_[prev[0][prev[2]], prev[1][prev[2]]])
            dist, _ = tree.query(np.c_[d["x"], d["y"]], distance_upper_bound=radius)
            m = m | (np.isfinite(dist) & switched(d, 0.0, 0.0, ratio))
        masks.append(m)
        prev = (d["x"], d["y"], m)
    return masks


def flow(d: dict, m: np.ndarray, unit: int) -> tuple[np.ndarray, np.ndarray]:
    """(dh_u, h_u dtheta) with the test's answer where ``m``."""
    dh = np.where(m, d["gain"][unit], d["off"][unit])
    return dh, d["h"][unit] * np.where(m, d["gain"][2], d["off"][2])


def score(pairs: list[dict], masks: list) -> tuple[dict, list]:
    """Mean-flow error per mover, cam1 / cam2 (%), and static mean EPE, cam1 / cam2."""
    sums, static = {}, [[], []]
    for d, m in zip(pairs, masks, strict=True):
        for u in (0, 1):
            (dh, ht), (tdh, tht) = flow(d, m, u), d["truth"][u]
            ok = np.isfinite(tdh) & np.isfinite(tht)
            static[u].append(np.hypot(dh - tdh, ht - tht)[ok & ~d["mover"]])
            for name in np.unique(d["name"][ok & d["mover"]]):
                s = ok & (d["name"] == name)
                acc = sums.setdefault(name, np.zeros((2, 5)))
                acc[u] += [dh[s].sum(), ht[s].sum(), tdh[s].sum(), tht[s].sum(), s.sum()]
    err = {}
    for name, acc in sums.items():
        e, te = acc[:, :2] - acc[:, 2:4], acc[:, 2:4]
        err[name] = 100.0 * np.hypot(*e.T) / np.hypot(*te.T)
    return err, [np.concatenate(s).mean() for s in static]


def by_share(share: float):
    """The built gates with range-edge pools those whose range test drops more than
    ``share`` of the neighbours (``EDGE_SHARE`` is 0.25)."""

    def rule(d):
        return switched(dict(d, edge=d["share"] > share), 10.0, 20.0)

    return rule


def by_p(alpha: float):
    """F_U above the 1 - ``alpha`` point of F(1, n_eff - 6), ratio and dof as built."""

    def rule(d):
        with np.errstate(invalid="ignore"):
            gate = f_dist.isf(alpha, 1.0, np.maximum(d["dof"], 1e-9))
            return switched(d, 0.0, 0.0) & (d["F"] > gate)

    return rule


RULES = {
    "built (decouple_gain_tol 20: edge 10 | 20)": lambda d: switched(d, 10.0, 20.0),
    **{
        f"decouple_gain_tol {tol} (edge {tol / 2:g} | {tol})": (
            lambda d, tol=tol: switched(d, tol / 2.0, float(tol))
        )
        for tol in (18, 17, 16, 15, 14, 13, 12, 10)
    },
    "edge 10 | 15": lambda d: switched(d, 10.0, 15.0),
    "edge 9 | 15": lambda d: switched(d, 9.0, 15.0),
    "edge 8 | 15": lambda d: switched(d, 8.0, 15.0),
    "edge 10 | 10": lambda d: switched(d, 10.0, 10.0),
    "edge 2 | 2": lambda d: switched(d, 2.0, 2.0),
    "EDGE_SHARE 0.1": by_share(0.1),
    "EDGE_SHARE 0": by_share(0.0),
    "p 0.01": by_p(0.01),
    "p 0.002": by_p(0.002),
    "p 0.001": by_p(0.001),
    "ratio 1.5, edge 10 | 20": lambda d: switched(d, 10.0, 20.0, 1.5),
    "ratio 1.5, edge 2 | 2": lambda d: switched(d, 2.0, 2.0, 1.5),
    "ratio 1.25, edge 10 | 10": lambda d: switched(d, 10.0, 10.0, 1.25),
    "ratio 1.25, edge 2 | 2": lambda d: switched(d, 2.0, 2.0, 1.25),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--frames", default="0,1,2", help="first frames of the pairs (0,1,2)")
    ap.add_argument("--object", default="ring", help="the mover whose points are listed")
    args = ap.parse_args()
    frames = [int(v) for v in args.frames.split(",")]
    data = {p: capture(p, frames) for p in args.datasets}
    print("scene pair point | F_U dof ratio edge-share edge | stopped by | EPE cam1 without -> "
          "with the answer, cam2 the same | pool: share switched as built")  # fmt: skip
    for pairs in data.values():
        for d in pairs:
            built = switched(d, 10.0, 20.0)
            e = [[np.hypot(*(np.array(flow(d, np.full(built.size, s), u)) - d["truth"][u]))
                  for s in (False, True)] for u in (0, 1)]  # fmt: skip
            for i in np.flatnonzero(d["name"] == args.object):
                gate = 10.0 if d["edge"][i] else 20.0
                why = [
                    s
                    for s, bad in (
                        ("no fit", not d["fin"][i]),
                        (f"F_U <= {gate:.0f}", not d["F"][i] > gate),
                        ("dof", not d["dof"][i] >= 4),
                        ("ratio", not d["ratio"][i] >= 2),
                    )
                    if bad
                ]
                nb = d["idx"][i][(d["idx"][i] < built.size) & (d["w"][i] > 0)]
                epe = f"{e[0][0][i]:.3f} -> {e[0][1][i]:.3f}, {e[1][0][i]:.3f} -> {e[1][1][i]:.3f}"
                print(f"{d['scene']} {d['t']} {i} | {d['F'][i]:.1f} {d['dof'][i]:.1f} "
                      f"{d['ratio'][i]:.2f} {d['share'][i]:.2f} {int(d['edge'][i])} | "
                      f"{', '.join(why) or 'switched'} | {epe} | "
                      f"{built[nb].mean():.2f} of {nb.size}")  # fmt: skip
    print("static points with ratio >= 2 and n_eff - 6 >= 4 that the built F_U gate stops")
    for pairs in data.values():
        for d in pairs:
            stopped = switched(d, 0.0, 0.0) & ~switched(d, 10.0, 20.0) & ~d["mover"]
            e = [np.hypot(*(np.array(flow(d, np.full(d["F"].size, s), 0)) - d["truth"][0]))
                 for s in (False, True)]  # fmt: skip
            for i in np.flatnonzero(stopped):
                print(f"{d['scene']} {d['t']} {d['name'][i]} | {d['F'][i]:.1f} {d['dof'][i]:.1f} "
                      f"{d['ratio'][i]:.2f} {d['share'][i]:.2f} {int(d['edge'][i])} | "
                      f"cam1 {e[0][i]:.3f} -> {e[1][i]:.3f}")  # fmt: skip
    rules = dict(RULES)
    rules["tol 10, then 8 px of the previous pair's"] = "after"
    for name, rule in rules.items():
        row = []
        for pairs in data.values():
            if rule == "after":
                masks = after(pairs, lambda d: switched(d, 5.0, 10.0))
            else:
                masks = [rule(d) for d in pairs]
            err, static = score(pairs, masks)
            n_static = sum(int((m & ~d["mover"]).sum()) for m, d in zip(masks, pairs, strict=True))
            movers = ", ".join(f"{k} {v[0]:.1f}/{v[1]:.1f}" for k, v in sorted(err.items()))
            movers = "; " + movers if movers else ""
            row.append(f"{pairs[0]['scene']}: {n_static} static switched, static "
                       f"{static[0]:.5f}/{static[1]:.5f}{movers}")  # fmt: skip
        print(f"{name} || " + " || ".join(row))


if __name__ == "__main__":
    main()
