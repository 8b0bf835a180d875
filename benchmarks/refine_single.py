"""The refinement's exact evaluations in float32 against float64, on rendered pairs.

:func:`omniflow.solve.refine.refine_moving` evaluates the fitted series exactly at its
points (:meth:`omniflow.paper.dct.DCTFit.value_and_gradient`), in float32 products by
default (``omniflow.solve.refine.SINGLE``). For each dataset and pair this prints, over
every point of the pair (each unit's series at the flow band, displaced by the
first solve's flow as the refinement does), the largest and rms difference of the
float32 evaluation from the float64 one: the value of frame t + 1, the residual
f_{t+1}(displaced) - f_t(point) of eq. (8) (a difference of two grey levels, the
quantity float32 rounding could hurt most), the gradient, and the residual's
difference over the gradient's magnitude (px, what it would move one point's flow
alone). With ``--time N``: ``estimate()`` on the first pair N times each way,
alternating float32 and float64 in one process (so the machine's load drifts
alike for both), medians of wall and CPU time and of the solve stage. Run::

    python benchmarks/refine_single.py /work/data/approach /work/data/independent_movers
    python benchmarks/refine_single.py /work/data/approach --pairs 0 --time 41
    python benchmarks/refine_single.py /work/data/approach --pairs 0 --points 273 932

``--points``: one evaluation at N random points of frame 0's series, each way.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _frames(ds, t):
    return ([ds.read_grey(j, "cam1") for j in (t, t + 1)],
            [ds.read_grey(j, "cam2") for j in (t, t + 1)])  # fmt: skip


def accuracy(directory: str, pairs: int) -> None:
    import omniflow.solve.at_matches as solve_mod
    import omniflow.solve.refine as refine
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate

    seen = []
    original = refine.refine_moving

    def capture(a, b, conf, **kw):
        seen.append((a, b, kw))
        return original(a, b, conf, **kw)

    solve_mod.refine_moving = capture
    ds = open_dataset(directory)
    try:
        for t in range(pairs):
            seen.clear()
            estimate(*_frames(ds, t), ds.rig, OmniFlowConfig(), t=0)
            a, b, kw = seen[-1]
            ok = np.isfinite(a) & np.isfinite(b)
            a0, b0 = np.where(ok, a, 0.0), np.where(ok, b, 0.0)
            k = kw["h2"] / kw["h1"]  # eq. (14)
            for cam, x, y, h, dh in (("cam1", kw["x1"], kw["y1"], kw["h1"], a0),
                                     ("cam2", kw["x2"], kw["y2"], kw["h2"], k * a0)):  # fmt: skip
                fr = kw[cam]
                xd, yd = fr["a"].unit.pixel_of_polar(h + dh, kw["theta"] + b0)
                fb = {s: fr["b"].fit.value_and_gradient(xd, yd, single=s) for s in (False, True)}
                fa = {s: fr["af"].fit.value_and_gradient(x, y, single=s) for s in (False, True)}
                res = {s: fb[s][0] - fa[s][0] for s in (False, True)}
                d_res = res[True] - res[False]
                d_val = fb[True][0] - fb[False][0]
                d_grad = max(np.abs(fb[True][i] - fb[False][i]).max() for i in (1, 2))
                grad = np.hypot(fb[False][1], fb[False][2])
                rms = np.sqrt(np.mean(d_res**2))
                print(
                    f"{ds.dir.name} pair {t} {cam}: {x.size} points;"
                    f" value max {np.abs(d_val).max():.1e}"
                    f" (|f| <= {np.abs(fb[False][0]).max():.2f});"
                    f" residual max {np.abs(d_res).max():.1e} rms {rms:.1e}"
                    f" (residual rms {np.sqrt(np.mean(res[False] ** 2)):.1e});"
                    f" gradient max {d_grad:.1e} (median |grad| {np.median(grad):.1e});"
                    f" residual / |grad| max {np.max(np.abs(d_res) / grad):.1e} px"
                )
    finally:
        solve_mod.refine_moving = original


def timing(directory: str, repeats: int) -> None:
    import os

    import omniflow.solve.refine as refine
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate

    ds = open_dataset(directory)
    f1, f2 = _frames(ds, 0)
    config = OmniFlowConfig()
    was = refine.SINGLE
    runs = {False: [], True: []}
    try:
        for i in range(repeats + 3):  # 3 warm-up rounds
            for single in (False, True):
                refine.SINGLE = single
                t0, c0 = time.perf_counter(), time.process_time()
                res = estimate(f1, f2, ds.rig, config, t=0)
                if i >= 3:
                    runs[single].append((time.perf_counter() - t0, time.process_time() - c0,
                                         res.timings["solve"]))  # fmt: skip
    finally:
        refine.SINGLE = was
    print(f"{ds.dir.name} pair 0, {repeats} alternating runs each, load {os.getloadavg()[0]:.1f}:")
    for single in (False, True):
        wall, cpu, solve = np.median(np.array(runs[single]), axis=0) * 1e3
        print(f"  {'float32' if single else 'float64'}: wall {wall:.1f} ms, CPU {cpu:.1f} ms,"
              f" solve stage {solve:.1f} ms")  # fmt: skip


def evaluation_time(directory: str, points: list[int], repeats: int = 51) -> None:
    """One value_and_gradient at N random points of frame 0's flow-band series (cam1),
    float64 and float32 alternating, one BLAS thread (as the refinement runs it)."""
    import omniflow.solve.refine as refine
    from omniflow.config import OmniFlowConfig
    from omniflow.fit.series import fit_band, grey_input, truncate
    from omniflow.io.dataset import open_dataset
    from omniflow.paper.dct import fit_dct

    ds = open_dataset(directory)
    config = OmniFlowConfig()
    unit = ds.rig.cam1
    frame = grey_input(ds.read_grey(0, "cam1"), "cam1", unit, config)
    fit = truncate(fit_dct(frame, band=fit_band(config)), config.flow_band, config.flow_taper)
    rng = np.random.default_rng(0)
    with refine._one_blas_thread():
        for n in points:
            h = rng.uniform(config.h_min, unit.r_m - config.rim_margin, n)
            x, y = unit.pixel_of_polar(h, rng.uniform(-np.pi, np.pi, n))
            ms = {False: [], True: []}
            for i in range(repeats + 3):
                for single in (False, True):
                    t0 = time.perf_counter()
                    fit.value_and_gradient(x, y, single=single)
                    if i >= 3:
                        ms[single].append((time.perf_counter() - t0) * 1e3)
            print(f"{ds.dir.name}: value_and_gradient at {n} points ({fit.Q} x {fit.P} series):"
                  f" float64 {np.median(ms[False]):.2f} ms, float32 {np.median(ms[True]):.2f} ms"
                  f" (medians of {repeats})")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--pairs", type=int, default=3, help="pairs (t, t + 1), t < PAIRS")
    parser.add_argument("--time", type=int, default=0, metavar="N",
                        help="also time estimate() N times each way (alternating)")  # fmt: skip
    parser.add_argument("--points", type=int, nargs="*", default=[], metavar="N",
                        help="also time one evaluation at N points each way")  # fmt: skip
    args = parser.parse_args(argv)
    for directory in args.datasets:
        accuracy(directory, args.pairs)
        if args.time:
            timing(directory, args.time)
        if args.points:
            evaluation_time(directory, args.points)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
