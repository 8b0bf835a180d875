"""Where ``decouple_gain_tol``'s test of eq. (14) passes, and what its two gates decide there.

For each dataset and pair (t, t + 1), t in ``--frames``: :func:`omniflow.pipeline.estimate`
with ``decouple_gain_tol`` None and with ``--tol`` (20) with the gates of
:mod:`omniflow.solve.gain` opened (``MIN_RESIDUAL_DOF`` just above 0 and ``MIN_RESIDUAL_RATIO``
1: F_U alone, as first built), its linear-gain fits taken from
:func:`omniflow.solve.decoupled.chained`. Prints every point whose F_U passes the gate (half of
it on range-edge pools, ``EDGE_GATE``): its object (moving or static), F_U, n_eff, the
residual ratio RSS_coupled / RSS_decoupled = 1 + F_U / (n_eff - 6), whether each gate
keeps it, the F statistic of the gain's three columns and its largest fitted term
(max |beta|, |beta_u|, |beta_h|), whether the answer keeps the gain (``MIN_GAIN_F``,
``MIN_GAIN_CHANGE``), and its endpoint error without the switch, with it, and with it
always answered with the gain (the rule off), cam1 and cam2, px::

    PYTHONPATH=$PWD python benchmarks/decouple_gain_points.py /work/data/approach \\
        /work/data/independent_movers --frames 0,1,2
"""

from __future__ import annotations

import argparse

import numpy as np

import omniflow.solve.decoupled as decoupled_mod
import omniflow.solve.gain as gain_mod
from omniflow.config import OmniFlowConfig
from omniflow.io.dataset import open_dataset
from omniflow.pipeline import estimate
from validation.inputs import Inputs, camera_model
from validation.sampling import sample_truth
from validation.scoring_derived import moving_objects


def _epe(cols, truth, n, unit):
    h, dh = ("h1", "dh1_dt") if unit == 1 else ("h2", "dh2_dt")
    return np.hypot(cols[dh][:n] - truth["gt.flow.dh"],
                    cols[h][:n] * cols["dtheta_dt"][:n] - truth["gt.flow.hdtheta"])  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--frames", default="0,1,2", help="first frames of the pairs (0,1,2)")
    ap.add_argument("--tol", type=float, default=20.0, help="decouple_gain_tol (20)")
    args = ap.parse_args()
    seen = {}
    chained, linear_gain = decoupled_mod.chained, decoupled_mod.decoupled_linear_gain

    def spy(fit, tol):
        seen["fit"] = dict(fit)
        return chained(fit, tol)

    def spy_pools(*a, **kw):
        seen["w"] = a[6]  # the pools' weights: n_eff
        return linear_gain(*a, **kw)

    plain_where = gain_mod._plain_where_no_gain

    def spy_plain(M, v, yy, x, rss, n_eff, min_conditioning):
        seen["gain_F"] = gain_mod._without_gain(M, v, yy, rss, n_eff, min_conditioning)[1]
        seen["term"] = np.abs(x[:, 3:6]).max(axis=1)
        return plain_where(M, v, yy, x, rss, n_eff, min_conditioning)

    decoupled_mod.chained, decoupled_mod.decoupled_linear_gain = spy, spy_pools
    gain_mod._plain_where_no_gain = spy_plain
    rule = gain_mod.MIN_GAIN_F, gain_mod.MIN_GAIN_CHANGE
    min_dof, min_ratio = gain_mod.MIN_RESIDUAL_DOF, gain_mod.MIN_RESIDUAL_RATIO
    gain_mod.MIN_RESIDUAL_DOF, gain_mod.MIN_RESIDUAL_RATIO = 1e-12, 1.0  # F_U alone
    print(
        "dataset pair object moving | F_U n_eff ratio edge | dof ratio | "
        "gain F, term, answer | EPE cam1 without -> with [gain always], cam2 the same"
    )
    for path in args.datasets:
        ds = open_dataset(path)
        camera = camera_model(ds.meta)
        inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
        movers = set(moving_objects(ds.meta))
        for t in (int(v) for v in args.frames.split(",")):
            g1 = [inputs.grey(j, "cam1") for j in (t, t + 1)]
            g2 = [inputs.grey(j, "cam2") for j in (t, t + 1)]
            off = estimate(g1, g2, ds.rig, OmniFlowConfig(decouple_gain_tol=None)).columns
            gain_mod.MIN_GAIN_F, gain_mod.MIN_GAIN_CHANGE = -np.inf, 0.0  # the rule off
            always = estimate(g1, g2, ds.rig, OmniFlowConfig(decouple_gain_tol=args.tol)).columns
            gain_mod.MIN_GAIN_F, gain_mod.MIN_GAIN_CHANGE = rule
            on = estimate(g1, g2, ds.rig, OmniFlowConfig(decouple_gain_tol=args.tol)).columns
            fit = seen["fit"]
            sel = np.flatnonzero(seen["w"].sum(axis=1) > 0)
            gain_F, term = np.full(fit["gain_F"].size, np.nan), np.full(fit["gain_F"].size, np.nan)
            gain_F[sel], term[sel] = seen["gain_F"], seen["term"]
            n = fit["gain_F"].size
            passed = chained(fit, args.tol)
            w = seen["w"]
            n_eff = 2.0 * w.sum(axis=1) ** 2 / (w * w).sum(axis=1)
            ratio = 1.0 + fit["gain_F"] / (n_eff - 6.0)
            tr = [sample_truth(ds.read_frame(t, c), on[x][:n], on[y][:n])
                  for c, x, y in (("cam1", "x", "y"), ("cam2", "x2", "y2"))]  # fmt: skip
            obj = np.rint(tr[0]["gt.object"]).astype(int)
            for i in np.flatnonzero(passed):
                name = ds.objects.get(int(obj[i]), str(obj[i]))
                keep_dof, keep_ratio = n_eff[i] - 6.0 >= min_dof, ratio[i] >= min_ratio
                e = [[_epe(c, tr[u - 1], n, u)[i] for c in (off, on, always)] for u in (1, 2)]
                keeps = gain_F[i] > rule[0] or term[i] >= rule[1]
                print(f"{ds.dir.name} {t} {name} {int(obj[i]) in movers} | {fit['gain_F'][i]:.1f} "
                      f"{n_eff[i]:.1f} {ratio[i]:.2f} {bool(fit['gain_edge'][i])} | "
                      f"{'keeps' if keep_dof else 'drops'} {'keeps' if keep_ratio else 'drops'} | "
                      f"{gain_F[i]:.2f} {term[i]:.4f} {'gain' if keeps else 'plain'} | "
                      f"{e[0][0]:.3f} -> {e[0][1]:.3f} [{e[0][2]:.3f}], "
                      f"{e[1][0]:.3f} -> {e[1][1]:.3f} [{e[1][2]:.3f}]")  # fmt: skip


if __name__ == "__main__":
    main()
