"""Probe: a brightness-change term in the pooled equations, against the truth.

Brightness constancy (eq. 8) fails where a surface changes brightness as it
moves (a body turning under fixed lights, a face driving towards a lamp). The
classic remedy models that change per pool: eq. (9) and (15) of every
neighbour j become

    p_j a + q_j c (+ slopes) + f_t,j = alpha + beta f_j

with one offset ``alpha`` (grey levels per frame) and/or one gain ``beta``
(per frame) per pool, shared by both units' rows (they see the same surface
point), solved with the flow. This probe runs omniflow (the configuration
given, defaults unless ``--set``) on each frame pair of a dataset, formed as
omnivalidate forms the images, captures the first solve's derivatives at its
points (before the refinement and the two-model test of eq. 14), samples the
image f there (the series of the gradients: the mean of frames t and t + 1 at
the flow band), and solves again in plain numpy weighted least squares over
k-d tree pools (:func:`omniflow.solve.pooled.neighbourhoods`, the configuration's
pool_k, radius r_m / 8, range test), with omniflow's local model (relative
radial flow, linear in the tangential offset) and its errors-in-variables
correction (``eiv="residual"``), for

* A: no brightness term (omniflow's first solve, re-coded),
* B: + alpha, C: + beta f, D: + alpha + beta f.

Scored against the truth at the cam1 and cam2 points, at the points where
every answer has a flow: per object the mean radial (dh) and tangential
(h dtheta) flow, estimated / true, over the frame pairs; cam1 / cam2 endpoint
error mean / median on the moving objects and on the static ones; cam1's
radial gain (:func:`validation.metrics.gain`) over the scene. "omniflow" is
omniflow's own final answer at the same points (refined where it moves a
pixel, eq. 14 tested), "first" its first solve, which A should reproduce
(the largest difference is printed).

"X+ref+dec": variant X carried through omniflow's later steps with the same
term: the refinement (:func:`omniflow.solve.refine.refine_moving`, at the points
omniflow refined, each linearised about X's own first flow, solved for the
total flow) and, at the points where omniflow switched to the decoupled model
of :mod:`omniflow.solve.decoupled`, that model (U, W, dtheta/dt) with the term.
"A+ref+dec" should reproduce omniflow's final answer. With ``--gate G``, also
B, C, D (+ref+dec) only where the F statistic of the brightness unknowns
against A (the pool's residual sum of squares, effective rows
(sum w)^2 / sum w^2 per unit, as the two-model test's) exceeds G, A
elsewhere; the median and 90th percentile of F per object are printed. Run::

    python benchmarks/probe_brightness.py /work/data/approach /work/data/independent_movers \
        /work/data/crossing /work/data/default --frames 0,1,2 --gate 10
"""

from __future__ import annotations

import argparse

import numpy as np

VARIANTS = {"A": (False, False), "B": (True, False), "C": (False, True), "D": (True, True)}


def pooled_brightness(d: dict, idx: np.ndarray, w: np.ndarray, *, model: str, scale: float,
                      offset: bool, gain: bool, noise: tuple[float, float],
                      min_conditioning: float, decoupled: bool = False,
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:  # fmt: skip
    """(dh1_dt, dh2_dt, dtheta_dt) of every point from its pool's weighted least squares,
    and the fit's residual sum of squares, effective rows and number of unknowns.

    ``d`` holds the point columns (f1_h ... f2_t, h1, h2, theta, f1, f2).
    Unknowns (a, c = h_1 b[, slopes u a, u c][, alpha][, beta]); rows of neighbour
    j: unit 1 (f1_h rel, f1_theta / h_1,i, ...), unit 2 (k_j f2_h rel, ...), as
    :func:`omniflow.solve.pooled.pooled_solution`; NaN where the pool has no solution.
    ``decoupled``: the two-model test's three-unknown model instead
    (:func:`omniflow.solve.decoupled.fits_from_sums`: (U, h_1,i W, c), dh_u = U - h_u W,
    constant model, no bias compensation), eq. (14) not assumed.
    """
    n = d["h1"].size
    ext = {c: np.append(v, 0.0) for c, v in d.items()}
    ext["h1"][n] = 1.0
    hi = d["h1"][:, None]
    rel = ext["h1"][idx] / hi
    k = ext["h2"] / ext["h1"]
    u = ((ext["theta"][idx] - d["theta"][:, None] + np.pi) % (2 * np.pi) - np.pi) * hi / scale
    units = []
    for u_ in (1, 2):
        fh, q, t, f, h = (ext[c] for c in (f"f{u_}_h", f"f{u_}_theta", f"f{u_}_t", f"f{u_}",
                                           f"h{u_}"))  # fmt: skip
        p = fh if u_ == 1 else k * fh  # eq. (14): dh_2 = k dh_1
        pj, qj = p[idx] * rel, q[idx] / hi
        cols = [pj, qj]
        if decoupled:  # (f_h, -f_h h_u,j / h_1,i, f_theta / h_1,i) . (U, h_1,i W, c)
            cols = [fh[idx], -fh[idx] * h[idx] / hi, qj]
        elif model == "linear":
            cols += [pj * u, qj * u]
        if offset:
            cols.append(-np.ones_like(pj))
        if gain:
            cols.append(-f[idx])
        units.append((np.stack(cols, axis=-1), -t[idx]))
    X = np.stack([units[0][0], units[1][0]], axis=2)  # (N, K, 2, P)
    y = np.stack([units[0][1], units[1][1]], axis=2)  # (N, K, 2)
    M = np.einsum("nkup,nkuq,nk->npq", X, X, w)
    v = np.einsum("nkup,nku,nk->np", X, y, w)
    sol = _solve(M, v, min_conditioning)
    # the pool's residual sum of squares at the (plain) solution: sum w y^2 - x . v
    rss = np.einsum("nku,nku,nk->n", y, y, w) - np.einsum("np,np->n", sol, v)
    fit = {"rss": rss, "n_eff": 2.0 * w.sum(axis=1) ** 2 / (w * w).sum(axis=1),
           "unknowns": X.shape[-1]}  # fmt: skip
    if decoupled:
        kk = k[:n]
        return sol[:, 0] - sol[:, 1], sol[:, 0] - kk * sol[:, 1], sol[:, 2] / d["h1"], fit
    a, c = sol[:, 0], sol[:, 1]
    if noise[0] > 0 or noise[1] > 0:  # eiv="residual": omniflow's bias compensation
        ok = np.isfinite(a) & np.isfinite(c)
        res = np.einsum("nkup,np->nku", X[:, :1], sol) - y[:, :1]  # each point's own rows
        var = [float(np.median(res[ok, 0, j] ** 2)) / 0.455 / 2.0 for j in range(2)]
        n1, n2 = noise[0] * var[0], noise[1] * var[1]
        m = 3 if model == "linear" else 1
        wsum = [w.sum(axis=1), (w * u).sum(axis=1), (w * u * u).sum(axis=1)][:m]
        per_row = [n1 * s + n2 * k[:n] ** 2 * s for s in wsum]  # (N,) per power of u
        Mc = M.copy()
        # the gradient columns: a (0), c (1), u a (2), u c (3); power of u = i + j
        blocks = [(0, 2), (1, 3)] if model == "linear" else [(0,), (1,)]
        for block in blocks:
            for ii, ci in enumerate(block):
                for jj, cj in enumerate(block):
                    Mc[:, ci, cj] -= per_row[ii + jj]
        ac, cc = _solve(Mc, v, min_conditioning, positive=True)[:, :2].T
        strong = (M[:, 0, 0] > 2.0 * per_row[0]) & (M[:, 1, 1] > 2.0 * per_row[0])
        use = strong & np.isfinite(ac) & np.isfinite(cc)
        a, c = np.where(use, ac, a), np.where(use, cc, c)
    return a, k[:n] * a, c / d["h1"], fit


def _solve(M, v, min_conditioning, positive=False):
    """Solve the batched normal equations (all unknowns, shape (N, P)); NaN where the
    Schur complement on (a, c) (the information left on the flow once the other
    unknowns are free) is singular or
    its eigenvalue ratio is below ``min_conditioning``; with ``positive`` also where M
    is not positive definite."""
    scale = np.sqrt(np.abs(np.einsum("npp->np", M)))
    scale = np.where(scale > 0, scale, 1.0)
    Ms = M / scale[:, :, None] / scale[:, None, :]
    lam = np.linalg.eigvalsh(Ms)
    ok = lam[:, 0] > 1e-12 * lam[:, -1]
    if positive:
        ok &= lam[:, 0] > 0
    eye = np.eye(M.shape[1])
    Mi = np.linalg.inv(np.where(ok[:, None, None], M, eye))
    S = np.linalg.inv(Mi[:, :2, :2])  # Schur complement on (a, c)
    ls = np.linalg.eigvalsh(S)
    with np.errstate(divide="ignore", invalid="ignore"):
        conf = np.nan_to_num(ls[:, 0] / ls[:, 1])
    ok &= (conf >= min_conditioning) & (conf > 0) & (ls[:, 0] > 0)
    return np.where(ok[:, None], np.einsum("npq,nq->np", Mi, v), np.nan)


def refine(a, b, call, d, kw):
    """:func:`omniflow.solve.refine.refine_moving`'s step from the flow (a, b), with the pools'
    brightness term of ``kw`` (:func:`pooled_brightness`): at the points omniflow
    refined (``call``: its arguments and answer), with the same group of pool members,
    each linearised about its own flow in (a, b), solved for the total flow.
    Returns (dh1_dt, dh2_dt, dtheta_dt)."""
    from omniflow.solve import refine as ref
    from omniflow.solve.pooled import neighbourhoods

    (_, _, _, c), sel = call
    n = a.size
    group = sel.copy()
    if sel.any() and c["pools"] is not None:
        idx, w = c["pools"]
        members = idx[sel][w[sel] > 0]
        group[members[members < n]] = True
    i = np.flatnonzero(group)
    if i.size == 0:
        return a, d["h2"] / d["h1"] * a, b
    cfg, h1, h2 = c["config"], d["h1"][i], d["h2"][i]
    ai, bi = np.nan_to_num(a[i], posinf=0.0, neginf=0.0), np.nan_to_num(b[i], posinf=0.0,
                                                                         neginf=0.0)  # fmt: skip
    k = h2 / h1
    rows = []
    for u, cam, x, y, hu, du in ((1, c["cam1"], c["x1"], c["y1"], h1, ai),
                                 (2, c["cam2"], c["x2"], c["y2"], h2, k * ai)):  # fmt: skip
        q_h, q_th, e = ref._unit_rows(cam, x[i], y[i], hu, du, d["theta"][i], bi, cfg)
        rows += [(f"f{u}_h", q_h), (f"f{u}_theta", q_th), (f"f{u}_t", e - q_h * du - q_th * bi)]
    sub = dict(rows, h1=h1, h2=h2, theta=d["theta"][i], f1=d["f1"][i], f2=d["f2"][i])
    radius = kw["scale"]
    idx, w = neighbourhoods(c["x1"][i], c["y1"][i], k=cfg.pool_k, radius=radius, r=c["r"][i],
                            range_tol=cfg.pool_range_tol)  # fmt: skip
    an, _, bn, _ = pooled_brightness(sub, idx, w, **kw)
    step = np.isfinite(an) & np.isfinite(bn)
    keep = sel[i] & step & np.isfinite(a[i]) & np.isfinite(b[i])
    a, b = a.copy(), b.copy()
    a[i], b[i] = np.where(keep, an, a[i]), np.where(keep, bn, b[i])
    return a, d["h2"] / d["h1"] * a, b


def run_pair(ds, inputs, t, config, seen, args):
    """omniflow on pair t, the first solve captured; the variants solved again."""
    from omniflow.fit.sampling import sample_f
    from omniflow.pipeline import estimate
    from omniflow.solve.pooled import neighbourhoods

    seen.clear()
    g1 = [inputs.grey(j, "cam1") for j in (t, t + 1)]
    g2 = [inputs.grey(j, "cam2") for j in (t, t + 1)]
    final = estimate(g1, g2, ds.rig, config).columns
    rig, (cam1, cam2) = ds.rig, seen["cams"]
    x1, y1, theta, h1, h2, r, noise = seen["args"]
    derivs, first = seen["first"]
    d = dict(zip(("f1_h", "f1_theta", "f1_t", "f2_h", "f2_theta", "f2_t"), derivs, strict=True))
    x2, y2 = rig.cam2.pixel_of_polar(h2, theta)
    d.update(h1=h1, h2=h2, theta=theta, f1=sample_f(cam1["g"], x1, y1, config.sampling),
             f2=sample_f(cam2["g"], x2, y2, config.sampling))  # fmt: skip
    radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    idx, w = neighbourhoods(x1, y1, k=config.pool_k, radius=radius, r=r,
                            range_tol=config.pool_range_tol)  # fmt: skip
    floor = max(config.min_conditioning, config.pool_min_conditioning)
    eiv = noise if config.eiv == "residual" else (0.0, 0.0)
    # omniflow's final answer, at the points it kept (matched by position)
    xy = zip(final["x"], final["y"], strict=True)
    key = {(float(a), float(b)): i for i, (a, b) in enumerate(xy)}
    pos = np.array([key.get((float(a), float(b)), -1) for a, b in zip(x1, y1, strict=True)])
    got = pos >= 0
    fin = {c: np.where(got, final[c][pos], np.nan) for c in ("dh1_dt", "dh2_dt", "dtheta_dt")}
    switched = got & (np.where(got, final["coupled"][pos], 1.0) == 0.0)
    flows = {"omniflow": (fin["dh1_dt"], fin["dh2_dt"], fin["dtheta_dt"]),
             "first": (first[0], h2 / h1 * first[0], first[1])}  # fmt: skip
    fits, stats = {}, {}
    for name, (offset, gain) in VARIANTS.items():
        kw = dict(model=config.pool_model, scale=radius, offset=offset, gain=gain, noise=eiv,
                  min_conditioning=floor)  # fmt: skip
        *flows[name], fit = pooled_brightness(d, idx, w, **kw)
        *dec, fit_dec = pooled_brightness(d, idx, w, **{**kw, "model": "constant"},
                                          decoupled=True)  # fmt: skip
        # omniflow's refinement where it refined, with the same term, then (where
        # omniflow switched to the decoupled model) that model with the term
        ref = refine(flows[name][0], flows[name][2], seen["refine"], d, kw)
        flows[name + "+ref+dec"] = tuple(np.where(switched, v, c)
                                         for v, c in zip(dec, ref, strict=True))  # fmt: skip
        fits[name] = {c: np.where(switched, fit_dec[c], fit[c]) for c in ("rss", "n_eff")}
        fits[name]["unknowns"] = np.where(switched, fit_dec["unknowns"], fit["unknowns"])
    for name in ("B", "C", "D"):  # F statistic of the brightness unknowns against A
        f, f0 = fits[name], fits["A"]
        extra = f["unknowns"] - f0["unknowns"]
        with np.errstate(divide="ignore", invalid="ignore"):
            stats[name] = ((f0["rss"] - f["rss"]) / extra) / (
                f["rss"] / (f["n_eff"] - f["unknowns"])
            )
        if args.gate is not None:  # the term only where its F statistic passes the gate
            use = stats[name] > args.gate
            flows[f"{name}+ref+dec, F>{args.gate:g}"] = tuple(
                np.where(use, v, c) for v, c in zip(flows[name + "+ref+dec"],
                                                    flows["A+ref+dec"], strict=True))  # fmt: skip
    pts = dict(x1=x1, y1=y1, x2=x2, y2=y2, h1=h1, h2=h2, switched=switched, F=stats)
    return pts, flows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--frames", default="0,1,2", help="first frames of the pairs")
    parser.add_argument("--set", default="", help="config fields, e.g. pool_model=constant")
    parser.add_argument("--gate", type=float, default=None,
                        help="also B, C, D (+dec) only where the brightness unknowns' F "
                             "statistic exceeds this, A elsewhere")  # fmt: skip
    args = parser.parse_args()

    import omniflow.pipeline as pipeline
    import omniflow.solve.at_matches as solve_mod
    from omniflow.cli.common import config_from_settings
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from validation.inputs import Inputs, camera_model
    from validation.metrics import gain as gain_of
    from validation.sampling import sample_truth
    from validation.scoring_derived import moving_objects

    config = config_from_settings(args.set) if args.set else OmniFlowConfig()
    seen: dict = {}
    flow_at_matches, make_solver = solve_mod.flow_at_matches, solve_mod.make_solver

    def capture_flow(matches, rig, cam1, cam2, cfg):
        seen.setdefault("cams", (cam1, cam2))
        return flow_at_matches(matches, rig, cam1, cam2, cfg)

    def capture_solver(rig, cfg, x1, y1, theta, h1, h2, r, noise=(0.0, 0.0), **kw):
        solve = make_solver(rig, cfg, x1, y1, theta, h1, h2, r, noise, **kw)
        if "args" in seen:  # the refinement's solver
            return solve

        def wrapped(*derivs):
            out = solve(*derivs)
            seen.setdefault("first", (derivs, out))
            return out

        seen["args"] = (x1, y1, theta, h1, h2, r, noise)
        wrapped.pools = solve.pools
        return wrapped

    refine_moving = solve_mod.refine_moving

    def capture_refine(a, b, conf, **kw):
        out = refine_moving(a, b, conf, **kw)
        seen.setdefault("refine", ((a, b, conf, kw), out[3]))
        return out

    pipeline.flow_at_matches, solve_mod.make_solver = capture_flow, capture_solver
    solve_mod.refine_moving = capture_refine
    names = ["omniflow", "first", *VARIANTS, *(v + "+ref+dec" for v in VARIANTS)]
    if args.gate is not None:
        names += [f"{v}+ref+dec, F>{args.gate:g}" for v in ("B", "C", "D")]
    for directory in args.datasets:
        ds = open_dataset(directory)
        camera = camera_model(ds.meta)
        inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
        movers = set(moving_objects(ds.meta))
        rows: dict[str, list] = {n: [] for n in names}
        truth_rows, objs, diffs, fstats = [], [], {"first": [], "omniflow": []}, {}
        for t in (int(v) for v in args.frames.split(",")):
            pts, flows = run_pair(ds, inputs, t, config, seen, args)
            tr1 = sample_truth(ds.read_frame(t, "cam1"), pts["x1"], pts["y1"])
            tr2 = sample_truth(ds.read_frame(t, "cam2"), pts["x2"], pts["y2"])
            ok = (tr1["gt.flow.valid"] > 0.5) & (tr2["gt.flow.valid"] > 0.5)
            ok &= tr1["bilinear_ok"] & tr2["bilinear_ok"]
            for a, a2, b in flows.values():
                ok &= np.isfinite(a) & np.isfinite(a2) & np.isfinite(b)
            for ref, name, mask in (("first", "A", np.ones_like(ok)),
                                    ("omniflow", "A+ref+dec", np.ones_like(ok))):  # fmt: skip
                (fa, _, fb), (aa, _, ab) = flows[ref], flows[name]
                both = np.isfinite(fa) & np.isfinite(aa) & mask
                diffs[ref].append(np.hypot(fa - aa, pts["h1"] * (fb - ab))[both])
            for n in names:
                a, a2, b = flows[n]
                rows[n].append(np.stack([a, pts["h1"] * b, a2, pts["h2"] * b])[:, ok])
            tr = (tr1["gt.flow.dh"], tr1["gt.flow.hdtheta"], tr2["gt.flow.dh"],
                  tr2["gt.flow.hdtheta"])  # fmt: skip
            truth_rows.append(np.stack(tr)[:, ok])
            objs.append(np.rint(tr1["gt.object"][ok]).astype(int))
            for name, f in pts["F"].items():
                fstats.setdefault(name, []).append(f[ok])
        true = np.concatenate(truth_rows, axis=1)
        obj = np.concatenate(objs)
        scene = ds.meta.get("scene", {}).get("name", directory)
        print(f"== {scene} ({directory}), pairs {args.frames}, {obj.size} points "
              f"(every answer finite, truth valid); config {args.set or 'defaults'}")  # fmt: skip
        for ref, name in (("first", "A"), ("omniflow", "A+ref+dec")):
            diff = np.concatenate(diffs[ref])
            if diff.size:
                what = "first solve" if ref == "first" else "answer"
                print(f"   {name} vs omniflow's {what}, |difference| cam1 px: "
                      f"median {np.median(diff):.2e}, 99 % {np.percentile(diff, 99):.2e}, "
                      f"max {diff.max():.2e} over {diff.size}")  # fmt: skip
        static = ~np.isin(obj, list(movers))
        groups = [(ds.objects.get(int(o), str(o)), obj == o) for o in sorted(movers)
                  if (obj == o).sum() > 0] + [("static", static)]  # fmt: skip
        head = "".join(f" {g[:10]:>17s}" for g, _ in groups)
        print(f"   {'':27s}{head}")
        for c, cam in ((0, "true cam1"), (2, "true cam2")):
            print(
                f"   {cam:27s}"
                + "".join(
                    f" {true[c, m].mean():+7.3f}/{true[c + 1, m].mean():+7.3f}  " for _, m in groups
                )
            )
        print(f"   {'n':27s}" + "".join(f" {m.sum():17d}" for _, m in groups))
        for name, parts in fstats.items():
            f = np.concatenate(parts)
            print(f"   F of {name} (median; 90 %)".ljust(30) + "".join(
                f" {np.nanmedian(f[m]):7.1f}; {np.nanpercentile(f[m], 90):7.1f}"
                for _, m in groups))  # fmt: skip
            if args.gate is not None:
                print(f"   share F > {args.gate:g}".ljust(30) + "".join(
                    f" {100 * np.mean(f[m] > args.gate):16.1f}%" for _, m in groups))  # fmt: skip
        print("   (each cell: mean dh / mean h dtheta, px per frame; cam1, then cam2)")
        for n in names:
            est = np.concatenate(rows[n], axis=1)
            cells = "".join(f" {est[0, m].mean():+7.3f}/{est[1, m].mean():+7.3f}  "
                            for _, m in groups)  # fmt: skip
            e1 = np.hypot(*(est[:2] - true[:2]))
            e2 = np.hypot(*(est[2:] - true[2:]))
            mv = ~static
            g = gain_of(est[0], true[0])["gain"]
            g2 = gain_of(est[2], true[2])["gain"]
            cells2 = "".join(f" {est[2, m].mean():+7.3f}/{est[3, m].mean():+7.3f}  "
                             for _, m in groups)  # fmt: skip
            print(f"   {n:27s}{cells}")
            print(f"   {'':27s}{cells2}")
            print(f"   {'':8s}EPE cam1/cam2 mean/median: static {e1[static].mean():.4f}/"
                  f"{np.median(e1[static]):.4f} {e2[static].mean():.4f}/"
                  f"{np.median(e2[static]):.4f}" + (
                      f"; movers {e1[mv].mean():.4f}/{np.median(e1[mv]):.4f} "
                      f"{e2[mv].mean():.4f}/{np.median(e2[mv]):.4f}" if mv.any() else "")
                  + f"; radial gain cam1/cam2 {g:.3f}/{g2:.3f}")  # fmt: skip
        print(flush=True)


if __name__ == "__main__":
    main()
