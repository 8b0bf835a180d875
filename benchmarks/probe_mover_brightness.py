"""Probe: richer per-pool brightness models on the movers, against the truth.

A single gain per pool (``OmniFlowConfig.brightness_gate``, omniflow/solve/gain.py)
fixes approach's incoming face and most of the rolling ball but leaves the
ring, the poster and the spinner of independent_movers where they were. This
probe asks why, and whether a richer brightness model does better. It runs
omniflow (defaults unless ``--set``) on each frame pair as omnivalidate forms
the images, captures the first solve's derivatives at its points, samples the
image f there (the series of the gradients) and the truth, and

1. measures the brightness change along the true flow *as the equations see
   it*: r_u = f_u,h dh_u + f_u,theta dtheta + f_u,t, the residual of eq. (9)
   (u = 1) and eq. (15) (u = 2) at the true flow, at every point (grey levels
   of the flow band per frame). Per object: its mean, rms, and, per pool, the
   share of sum w r^2 that each brightness model's columns explain (the
   median over the object's pools), and the flow error that r alone causes
   under each model: the pooled solve with right side -r (omniflow's pool
   model, the flow columns plus the model's brightness columns), which is the
   part of the estimate's error due to the failed brightness constancy;

2. solves the pools again in numpy weighted least squares (k-d tree pools as
   omniflow's, linear local model, relative radial column, its
   errors-in-variables correction) with each brightness model, carried through
   omniflow's refinement and, where omniflow switched to it, the decoupled
   model (as benchmarks/probe_brightness.py):

   * A: none (omniflow, re-coded; the difference from its answer is printed),
   * C: a gain beta f_j per pool (omniflow/solve/gain.py),
   * BC: an offset and a gain, alpha + beta f_j,
   * L: a gain varying linearly across the pool,
     (beta + beta_u u_j + beta_h dh_j) f_j, with u_j the tangential and dh_j
     the radial offset of neighbour j from the point (px, over the pool
     radius, as the linear pool model's u),

   each ungated and gated by its F statistic against A (the extra unknowns'
   F, as omniflow.solve.gain) at ``--gates``; and "edge": the gain (C) with the low
   gate ``--edge-gate`` only where the pool lies on an object whose range
   differs from its surroundings (more than ``--edge-share`` of the pool's
   neighbours within the radius dropped by the range test), the high gate
   (the first of ``--gates``) elsewhere.

Scored at the points where every answer is finite and the truth valid, per
object: cam1 and cam2 mean radial dh and tangential h dtheta flow (px per
frame, estimated; the truth in the header) and mean endpoint error, and the
static objects' mean EPE. Run::

    python benchmarks/probe_mover_brightness.py /work/data/independent_movers \\
        /work/data/approach /work/data/crossing --frames 0,1,2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import probe_brightness as pb  # its batched solve

# brightness columns of each model (besides the flow's)
MODELS = {"A": (), "C": ("gain",), "BC": ("offset", "gain"), "L": ("gain", "gain_u", "gain_h")}
DEC_MODELS = ("A", "C", "L")  # with the decoupled model where its own test passes


def design(d: dict, idx: np.ndarray, *, model: str, scale: float, terms: tuple[str, ...],
           decoupled: bool = False, right: str = "t") -> tuple[np.ndarray, ...]:  # fmt: skip
    """The pools' design (N, K, 2, P), right sides (N, K, 2) and tangential offsets u.

    ``d`` holds the point columns (f1_h ... f2_t, h1, h2, theta, f1, f2[, r1, r2]).
    Flow unknowns (a, c = h_1 b[, u a, u c]) as :func:`omniflow.solve.pooled.pooled_solution`
    (or (U, h_1,i W, c) with ``decoupled``, :mod:`omniflow.solve.decoupled`), then the
    brightness unknowns of ``terms`` in order; both units' rows share them.
    ``right``: "t" the equations' right side -f_t, "r" the brightness change along
    the truth, -r (the error it alone causes)."""
    n = d["h1"].size
    ext = {c: np.append(v, 0.0) for c, v in d.items()}
    ext["h1"][n] = 1.0
    hi = d["h1"][:, None]
    rel = ext["h1"][idx] / hi
    k = ext["h2"] / ext["h1"]
    u = ((ext["theta"][idx] - d["theta"][:, None] + np.pi) % (2 * np.pi) - np.pi) * hi / scale
    dh = (ext["h1"][idx] - hi) / scale
    units = []
    for un in (1, 2):
        fh, q, f, h = (ext[c] for c in (f"f{un}_h", f"f{un}_theta", f"f{un}", f"h{un}"))
        p = fh if un == 1 else k * fh  # eq. (14): dh_2 = k dh_1
        pj, qj, fj = p[idx] * rel, q[idx] / hi, f[idx]
        cols = [pj, qj]
        if decoupled:  # (f_h, -f_h h_u,j / h_1,i, f_theta / h_1,i) . (U, h_1,i W, c)
            cols = [fh[idx], -fh[idx] * h[idx] / hi, qj]
        elif model == "linear":
            cols += [pj * u, qj * u]
        extra = {"offset": -np.ones_like(pj), "gain": -fj, "gain_u": -fj * u, "gain_h": -fj * dh}
        cols += [extra[t] for t in terms]
        rhs = ext[f"f{un}_t"] if right == "t" else ext[f"r{un}"]
        rhs = ext[f"f{un}_t"] - rhs if right == "o" else rhs  # "o": f_t less the change
        units.append((np.stack(cols, axis=-1), -rhs[idx]))
    X = np.stack([units[0][0], units[1][0]], axis=2)
    y = np.stack([units[0][1], units[1][1]], axis=2)
    return X, y, u


def pooled(d: dict, idx: np.ndarray, w: np.ndarray, *, model: str, scale: float,
           terms: tuple[str, ...], noise: tuple[float, float], min_conditioning: float,
           decoupled: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:  # fmt: skip
    """(dh1_dt, dh2_dt, dtheta_dt) from each pool with the brightness ``terms``, and
    the fit's rss, effective rows and unknowns (benchmarks/probe_brightness.py's
    solve, any brightness columns)."""
    X, y, u = design(d, idx, model=model, scale=scale, terms=terms, decoupled=decoupled)
    k = d["h2"] / d["h1"]
    M = np.einsum("nkup,nkuq,nk->npq", X, X, w)
    v = np.einsum("nkup,nku,nk->np", X, y, w)
    sol = pb._solve(M, v, min_conditioning)
    rss = np.einsum("nku,nku,nk->n", y, y, w) - np.einsum("np,np->n", sol, v)
    fit = {"rss": rss, "n_eff": 2.0 * w.sum(axis=1) ** 2 / (w * w).sum(axis=1),
           "unknowns": X.shape[-1], "x": sol}  # fmt: skip
    if decoupled:
        return sol[:, 0] - sol[:, 1], sol[:, 0] - k * sol[:, 1], sol[:, 2] / d["h1"], fit
    a, c = sol[:, 0], sol[:, 1]
    if noise[0] > 0 or noise[1] > 0:  # eiv="residual", as omniflow
        ok = np.isfinite(a) & np.isfinite(c)
        res = np.einsum("nkup,np->nku", X[:, :1], sol) - y[:, :1]
        var = [float(np.median(res[ok, 0, j] ** 2)) / 0.455 / 2.0 for j in range(2)]
        n1, n2 = noise[0] * var[0], noise[1] * var[1]
        m = 3 if model == "linear" else 1
        wsum = [w.sum(axis=1), (w * u).sum(axis=1), (w * u * u).sum(axis=1)][:m]
        per_row = [n1 * s + n2 * k**2 * s for s in wsum]
        Mc = M.copy()
        blocks = [(0, 2), (1, 3)] if model == "linear" else [(0,), (1,)]
        for block in blocks:
            for ii, ci in enumerate(block):
                for jj, cj in enumerate(block):
                    Mc[:, ci, cj] -= per_row[ii + jj]
        ac, cc = pb._solve(Mc, v, min_conditioning, positive=True)[:, :2].T
        strong = (M[:, 0, 0] > 2.0 * per_row[0]) & (M[:, 1, 1] > 2.0 * per_row[0])
        use = strong & np.isfinite(ac) & np.isfinite(cc)
        a, c = np.where(use, ac, a), np.where(use, cc, c)
    return a, k * a, c / d["h1"], fit


def r_analysis(d: dict, idx: np.ndarray, w: np.ndarray, *, model: str, scale: float,
               terms: tuple[str, ...], decoupled: bool = False,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Per pool: the share of sum w r^2 the brightness columns of ``terms`` explain
    alone (NaN for none), and the flow error r causes under the model (the plain
    pooled solve with right side -r): cam1 radial and tangential (h dtheta), px;
    ``decoupled``: under the decoupled model (constant) with the terms."""
    X, y, _ = design(d, idx, model="constant" if decoupled else model, scale=scale,
                     terms=terms, decoupled=decoupled, right="r")  # fmt: skip
    M = np.einsum("nkup,nkuq,nk->npq", X, X, w)
    v = np.einsum("nkup,nku,nk->np", X, y, w)
    err = pb._solve(M, v, 0.0)
    yy = np.einsum("nku,nku,nk->n", y, y, w)
    share = np.full(yy.size, np.nan)
    if terms:
        nb = len(terms)
        Mb, vb = M[:, -nb:, -nb:], v[:, -nb:]
        det_ok = np.abs(np.linalg.det(Mb)) > 0
        Mb = np.where(det_ok[:, None, None], Mb, np.eye(nb))
        xb = np.linalg.solve(Mb, vb[:, :, None])[:, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            share = np.where(det_ok, np.einsum("np,np->n", xb, vb) / yy, np.nan)
    if decoupled:  # dh_1 = U - h_1 W
        return share, err[:, 0] - err[:, 1], err[:, 2]
    return share, err[:, 0], err[:, 1]


def decomposition(d: dict, idx: np.ndarray, w: np.ndarray, *, model: str,
                  scale: float) -> dict[str, np.ndarray]:  # fmt: skip
    """cam1 radial flow of the plain pooled solve (no brightness term, no bias
    compensation) split into the part from the true flow ("perfect": right side
    -(f_t - r), brightness constancy exact) and the part from the brightness change
    ("r": right side -r); "t" = "perfect" + "r" (the equations' own right side), with
    the coupled model (eq. 14, ``model``) and with the decoupled one ("dec ...")."""
    out = {}
    for dec in (False, True):
        for right in ("t", "o", "r"):
            X, y, _ = design(d, idx, model="constant" if dec else model, scale=scale, terms=(),
                             decoupled=dec, right=right)  # fmt: skip
            M = np.einsum("nkup,nkuq,nk->npq", X, X, w)
            v = np.einsum("nkup,nku,nk->np", X, y, w)
            x = pb._solve(M, v, 0.0)
            name = {"t": "plain", "o": "perfect", "r": "r"}[right]
            out[("dec " if dec else "") + name] = x[:, 0] - x[:, 1] if dec else x[:, 0]
    return out


def refine(a, b, call, d, kw):
    """omniflow's refinement step from (a, b) with the brightness terms of ``kw``, at the
    points omniflow refined (benchmarks/probe_brightness.py's ``refine``, any terms)."""
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
    ai, bi = (np.nan_to_num(v[i], posinf=0.0, neginf=0.0) for v in (a, b))
    k = h2 / h1
    rows = []
    for u, cam, x, y, hu, du in ((1, c["cam1"], c["x1"], c["y1"], h1, ai),
                                 (2, c["cam2"], c["x2"], c["y2"], h2, k * ai)):  # fmt: skip
        q_h, q_th, e = ref._unit_rows(cam, x[i], y[i], hu, du, d["theta"][i], bi, cfg)
        rows += [(f"f{u}_h", q_h), (f"f{u}_theta", q_th), (f"f{u}_t", e - q_h * du - q_th * bi)]
    sub = dict(rows, h1=h1, h2=h2, theta=d["theta"][i], f1=d["f1"][i], f2=d["f2"][i])
    idx, w = neighbourhoods(c["x1"][i], c["y1"][i], k=cfg.pool_k, radius=kw["scale"],
                            r=c["r"][i], range_tol=cfg.pool_range_tol)  # fmt: skip
    an, _, bn, _ = pooled(sub, idx, w, **kw)
    keep = sel[i] & np.isfinite(an) & np.isfinite(bn) & np.isfinite(a[i]) & np.isfinite(b[i])
    a, b = a.copy(), b.copy()
    a[i], b[i] = np.where(keep, an, a[i]), np.where(keep, bn, b[i])
    return a, d["h2"] / d["h1"] * a, b


def run_pair(ds, inputs, t, config, seen, args):
    """omniflow on pair t, the first solve captured, the truth sampled; the models
    solved again and the brightness change along the truth analysed."""
    from omniflow.fit.sampling import sample_f
    from omniflow.pipeline import estimate
    from omniflow.solve.pooled import neighbourhoods
    from validation.sampling import sample_truth

    seen.clear()
    g1 = [inputs.grey(j, "cam1") for j in (t, t + 1)]
    g2 = [inputs.grey(j, "cam2") for j in (t, t + 1)]
    final = estimate(g1, g2, ds.rig, config).columns
    rig, (cam1, cam2) = ds.rig, seen["cams"]
    x1, y1, theta, h1, h2, r, noise = seen["args"]
    derivs, _ = seen["first"]
    d = dict(zip(("f1_h", "f1_theta", "f1_t", "f2_h", "f2_theta", "f2_t"), derivs, strict=True))
    x2, y2 = rig.cam2.pixel_of_polar(h2, theta)
    d.update(h1=h1, h2=h2, theta=theta, f1=sample_f(cam1["g"], x1, y1, config.sampling),
             f2=sample_f(cam2["g"], x2, y2, config.sampling))  # fmt: skip
    tr1 = sample_truth(ds.read_frame(t, "cam1"), x1, y1)
    tr2 = sample_truth(ds.read_frame(t, "cam2"), x2, y2)
    truth = np.stack([tr1["gt.flow.dh"], tr1["gt.flow.hdtheta"], tr2["gt.flow.dh"],
                      tr2["gt.flow.hdtheta"]])  # fmt: skip
    dth = truth[1] / h1
    # the brightness change along the truth as the equations see it: eq. (9), (15) residual
    d["r1"] = d["f1_h"] * truth[0] + d["f1_theta"] * dth + d["f1_t"]
    d["r2"] = d["f2_h"] * truth[2] + d["f2_theta"] * dth + d["f2_t"]
    valid = (tr1["gt.flow.valid"] > 0.5) & (tr2["gt.flow.valid"] > 0.5)
    valid &= tr1["bilinear_ok"] & tr2["bilinear_ok"] & np.isfinite(truth).all(axis=0)
    valid &= np.isfinite(d["r1"]) & np.isfinite(d["r2"])
    radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    idx, w = neighbourhoods(x1, y1, k=config.pool_k, radius=radius, r=r,
                            range_tol=config.pool_range_tol)  # fmt: skip
    # (c): pools on an object whose range differs from its surroundings
    _, w_all = neighbourhoods(x1, y1, k=config.pool_k, radius=radius, r=r, range_tol=None)
    n_all, n_kept = (w_all > 0).sum(axis=1), (w > 0).sum(axis=1)
    edge = (n_all - n_kept) > args.edge_share * n_all
    floor = max(config.min_conditioning, config.pool_min_conditioning)
    eiv = noise if config.eiv == "residual" else (0.0, 0.0)
    xy = zip(final["x"], final["y"], strict=True)
    key = {(float(a), float(b)): i for i, (a, b) in enumerate(xy)}
    pos = np.array([key.get((float(a), float(b)), -1) for a, b in zip(x1, y1, strict=True)])
    got = pos >= 0
    fin = {c: np.where(got, final[c][pos], np.nan) for c in ("dh1_dt", "dh2_dt", "dtheta_dt")}
    switched = got & (np.where(got, final["coupled"][pos], 1.0) == 0.0)
    flows = {"omniflow": (fin["dh1_dt"], fin["dh2_dt"], fin["dtheta_dt"])}
    fits, stats, ana, decs, firsts = {}, {}, {}, {}, {}
    # r analysis at the pools of the points where r is known (others: weight 0)
    dr = {**d, "r1": np.nan_to_num(d["r1"]), "r2": np.nan_to_num(d["r2"])}
    wr = np.where(np.append(valid, False)[idx], w, 0.0)
    parts = decomposition(dr, idx, wr, model=config.pool_model, scale=radius)
    for name, terms in MODELS.items():
        kw = dict(model=config.pool_model, scale=radius, terms=terms, noise=eiv,
                  min_conditioning=floor)  # fmt: skip
        ana[name] = r_analysis(dr, idx, wr, model=config.pool_model, scale=radius, terms=terms)
        first_fit = pooled(d, idx, w, **kw)
        firsts[name] = first_fit[3]
        dec = pooled(d, idx, w, **{**kw, "model": "constant"}, decoupled=True)
        ref = refine(first_fit[0], first_fit[2], seen["refine"], d, kw)
        decs[name] = dec
        if name in DEC_MODELS:
            ana["dec+" + name] = r_analysis(dr, idx, wr, model=config.pool_model, scale=radius,
                                            terms=terms, decoupled=True)  # fmt: skip
        flows[name] = tuple(np.where(switched, v, c) for v, c in zip(dec[:3], ref, strict=True))
        fits[name] = {c: np.where(switched, dec[3][c], first_fit[3][c]) for c in ("rss", "n_eff")}
        fits[name]["unknowns"] = np.where(switched, dec[3]["unknowns"], first_fit[3]["unknowns"])
    # the two-model test with the brightness terms: the decoupled model (U, h_1 W, c)
    # plus the terms of X against the coupled one (constant model, no term), the F of
    # the extra unknowns, as omniflow.solve.decoupled's test (X = A: that test itself)
    cpl = pooled(d, idx, w, model="constant", scale=radius, terms=(), noise=(0.0, 0.0),
                 min_conditioning=floor)[3]  # fmt: skip
    for name in DEC_MODELS:
        f = decs[name][3]
        with np.errstate(divide="ignore", invalid="ignore"):
            stats["dec+" + name] = ((cpl["rss"] - f["rss"]) / (f["unknowns"] - 2)) / (
                f["rss"] / (f["n_eff"] - f["unknowns"])
            )
        dec_ok = np.isfinite(decs[name][0]) & np.isfinite(decs[name][2])
        gates = [(f"F>{g:g}", g) for g in args.dec_gates]
        gates.append((f"edge F>{args.edge_gate:g}|{args.dec_gates[0]:g}",
                      np.where(edge, args.edge_gate, args.dec_gates[0])))  # fmt: skip
        for label, g in gates:
            use = dec_ok & (stats["dec+" + name] > g)
            flows[f"dec+{name} {label}"] = tuple(
                np.where(use, v, c) for v, c in zip(decs[name][:3], flows["A"], strict=True)
            )
    for name in list(MODELS)[1:]:
        f, f0 = fits[name], fits["A"]
        with np.errstate(divide="ignore", invalid="ignore"):
            stats[name] = ((f0["rss"] - f["rss"]) / (f["unknowns"] - f0["unknowns"])) / (
                f["rss"] / (f["n_eff"] - f["unknowns"])
            )
        for g in args.gates:
            use = stats[name] > g
            flows[f"{name} F>{g:g}"] = tuple(np.where(use, v, c) for v, c in
                                             zip(flows[name], flows["A"], strict=True))  # fmt: skip
    use = stats["C"] > np.where(edge, args.edge_gate, args.gates[0])
    flows[f"edge C F>{args.edge_gate:g}|{args.gates[0]:g}"] = tuple(
        np.where(use, v, c) for v, c in zip(flows["C"], flows["A"], strict=True))  # fmt: skip
    # eq. (14) tested given the brightness model: the decoupled model with the terms of
    # X against the coupled one with the same terms (constant model; one more unknown,
    # U). Then the chain "X/Y": dec+X where that F passes g, else the coupled model
    # with the terms of Y where Y's own F passes the high gate, else A
    for name in ("C", "L"):
        cx = pooled(d, idx, w, model="constant", scale=radius, terms=MODELS[name],
                    noise=(0.0, 0.0), min_conditioning=floor)[3]  # fmt: skip
        f = decs[name][3]
        with np.errstate(divide="ignore", invalid="ignore"):
            stats["U|" + name] = (cx["rss"] - f["rss"]) / (f["rss"] / (f["n_eff"] - f["unknowns"]))
    for x, y in (("C", "C"), ("L", "C"), ("L", "L")):
        dec_ok = np.isfinite(decs[x][0]) & np.isfinite(decs[x][2])
        gates = [(f"U>{g:g}", g) for g in args.dec_gates[:2]]
        gates.append((f"U edge>{args.edge_gate:g}|{args.dec_gates[0]:g}",
                      np.where(edge, args.edge_gate, args.dec_gates[0])))  # fmt: skip
        gain = stats[y] > args.gates[0]
        for label, g in gates:
            use = dec_ok & (stats["U|" + x] > g)
            flows[f"chain {x}/{y} {label}"] = tuple(
                np.where(use, v, np.where(gain, z, c))
                for v, z, c in zip(decs[x][:3], flows[y], flows["A"], strict=True))  # fmt: skip
    # the two tests together: dec+L where its own F against the coupled model passes
    # the second dec gate, or where U|L passes the edge gate at range-edge pools (the
    # first dec gate elsewhere); else C where its F passes the high gain gate; else A
    dec_ok = np.isfinite(decs["L"][0]) & np.isfinite(decs["L"][2])
    use = dec_ok & (
        (stats["dec+L"] > args.dec_gates[1])
        | (stats["U|L"] > np.where(edge, args.edge_gate, args.dec_gates[0]))
    )
    gain = stats["C"] > args.gates[0]
    label = f"dec>{args.dec_gates[1]:g}, U edge>{args.edge_gate:g}|{args.dec_gates[0]:g}"
    flows[f"both L/C {label}"] = tuple(
        np.where(use, v, np.where(gain, z, c))
        for v, z, c in zip(decs["L"][:3], flows["C"], flows["A"], strict=True))  # fmt: skip
    obj = np.rint(tr1["gt.object"]).astype(int)
    on = np.isin(obj, list(args.movers))  # the model wherever the truth says a mover
    for name in ("C", "BC", "L", *(f"dec+{m}" for m in DEC_MODELS)):
        new = decs[name[4:]][:3] if name.startswith("dec+") else flows[name]
        ok = on & np.isfinite(new[0]) & np.isfinite(new[2])
        flows[f"{name} @movers"] = tuple(np.where(ok, v, c)
                                         for v, c in zip(new, flows["A"], strict=True))  # fmt: skip
    for a, a2, b in flows.values():
        valid &= np.isfinite(a) & np.isfinite(a2) & np.isfinite(b)
    diff = np.hypot(
        flows["A"][0] - flows["omniflow"][0], h1 * (flows["A"][2] - flows["omniflow"][2])
    )
    est = {n: np.stack([a, h1 * b, a2, h2 * b]) for n, (a, a2, b) in flows.items()}
    # the coupled fits' statistics (benchmarks/probe_spinner_gate.py): the gain models'
    # RSS and terms, the pool's effective rows, its share of neighbours the range test drops
    coupled = {"rss_" + n: firsts[n]["rss"] for n in MODELS}
    coupled.update(n_eff=firsts["L"]["n_eff"], terms_L=firsts["L"]["x"][:, -3:],
                   beta_C=firsts["C"]["x"][:, -1], switched=switched,
                   edge_share=(n_all - n_kept) / np.maximum(n_all, 1))  # fmt: skip
    return dict(valid=valid, obj=obj, truth=truth, est=est, F=stats, edge=edge, ana=ana,
                coupled=coupled,
                parts=parts, switched=switched, k=h2 / h1,
                r=np.stack([d["r1"], d["r2"]]), f=np.stack([d["f1"], d["f2"]]),
                diff=diff[np.isfinite(diff)])  # fmt: skip


def capture(seen: dict) -> None:
    """Wrap omniflow.solve.at_matches's steps so that a run leaves its first solve's inputs and
    answer, its cameras and its refinement's call in ``seen`` (as probe_brightness)."""
    import omniflow.pipeline as pipeline
    import omniflow.solve.at_matches as solve_mod

    flow_at_matches, make_solver = solve_mod.flow_at_matches, solve_mod.make_solver
    refine_moving = solve_mod.refine_moving

    def capture_flow(matches, rig, cam1, cam2, cfg):
        seen.setdefault("cams", (cam1, cam2))
        return flow_at_matches(matches, rig, cam1, cam2, cfg)

    def capture_solver(rig, cfg, x1, y1, theta, h1, h2, r, noise=(0.0, 0.0), **kw):
        solve = make_solver(rig, cfg, x1, y1, theta, h1, h2, r, noise, **kw)
        if "args" in seen:
            return solve

        def wrapped(*derivs):
            out = solve(*derivs)
            seen.setdefault("first", (derivs, out))
            return out

        seen["args"] = (x1, y1, theta, h1, h2, r, noise)
        wrapped.pools = solve.pools
        return wrapped

    def capture_refine(a, b, conf, **kw):
        out = refine_moving(a, b, conf, **kw)
        seen.setdefault("refine", ((a, b, conf, kw), out[3]))
        return out

    pipeline.flow_at_matches, solve_mod.make_solver = capture_flow, capture_solver
    solve_mod.refine_moving = capture_refine


def report(ds, directory, parts, movers, frames):
    """Print the brightness-change analysis and the flow table of one dataset."""
    cat = lambda key: np.concatenate([p[key][..., p["valid"]] for p in parts], axis=-1)  # noqa: E731
    obj, true, r, f = cat("obj"), cat("truth"), cat("r"), cat("f")
    edge = cat("edge")
    static = ~np.isin(obj, list(movers))
    groups = [(ds.objects.get(int(o), str(o)), obj == o) for o in sorted(movers)
              if (obj == o).sum() > 0] + [("static", static)]  # fmt: skip
    diff = np.concatenate([p["diff"] for p in parts])
    scene = ds.meta.get("scene", {}).get("name", directory)
    print(f"== {scene} ({directory}), pairs {frames}, {obj.size} points; A vs omniflow's "
          f"answer |difference| cam1 px max {diff.max():.1e}")  # fmt: skip
    print(
        "-- brightness change along the truth, r (eq. 9 / 15 residual at the true flow), cam1; cam2"
    )
    print(
        f"   {'object':10s} {'n':>5s} {'edge%':>5s} {'mean r/f %':>13s} {'rms r/f %':>11s} "
        f"{'share of r explained (median pool) C / BC / L':>47s} "
        f"{'radial err from r: A / C / BC / L | dec A / C / L (cam1)':>60s} "
        f"{'tang. err A / C / L | dec A / C / L':>40s}"
    )
    rf = r / f  # the change per frame relative to the image there
    rms = lambda v: 100 * float(np.sqrt(np.mean(v * v)))  # noqa: E731
    for g, m in groups:
        sh, er, et = ({n: np.concatenate([p["ana"][n][j][p["valid"]] for p in parts])[m]
                       for n in parts[0]["ana"]} for j in range(3))  # fmt: skip
        print(f"   {g[:10]:10s} {m.sum():5d} {100 * edge[m].mean():5.0f} "
              f"{100 * rf[0, m].mean():+6.2f};{100 * rf[1, m].mean():+6.2f} "
              f"{rms(rf[0, m]):5.2f};{rms(rf[1, m]):5.2f} "
              + " ".join(f"{np.nanmedian(sh[n]):14.2f}" for n in ("C", "BC", "L"))
              + "   " + " ".join(f"{np.nanmean(er[n]):+6.3f}" for n in MODELS) + " |"
              + " ".join(f"{np.nanmean(er['dec+' + n]):+6.3f}" for n in DEC_MODELS)
              + "   " + " ".join(f"{np.nanmean(et[n]):+6.3f}" for n in ("A", "C", "L")) + " |"
              + " ".join(f"{np.nanmean(et['dec+' + n]):+6.3f}" for n in DEC_MODELS))  # fmt: skip
    print(
        "-- cam1 radial flow, first solve without bias compensation, split: perfect "
        "brightness constancy + the change r; coupled (eq. 14) | decoupled"
    )
    print(
        f"   {'object':10s} {'true':>7s} {'k dh1':>7s} {'dh2':>7s} {'switched':>8s}  "
        f"{'plain = perfect + r':>27s} | {'dec: plain = perfect + r':>27s}"
    )
    sw = cat("switched")
    k = cat("k")
    for g, m in groups:
        dec = {n: np.concatenate([p["parts"][n][p["valid"]] for p in parts])[m]
               for n in parts[0]["parts"]}  # fmt: skip
        print(f"   {g[:10]:10s} {true[0, m].mean():+7.3f} {(k[m] * true[0, m]).mean():+7.3f} "
              f"{true[2, m].mean():+7.3f} {100 * sw[m].mean():7.0f}%  "
              + " ".join(f"{np.nanmean(dec[n]):+8.3f}" for n in ("plain", "perfect", "r"))
              + " | " + " ".join(f"{np.nanmean(dec[n]):+8.3f}"
                                 for n in ("dec plain", "dec perfect", "dec r")))  # fmt: skip
    print(
        "-- F of each model against A (dec+X: the decoupled model with X's terms against "
        "the coupled one; U|X: the decoupled against the coupled, both with X's terms), "
        f"median / 90 %; share (%) above {parts[0]['gates']}"
    )
    for n in [*list(MODELS)[1:], *(f"dec+{m}" for m in DEC_MODELS), "U|C", "U|L"]:
        F = np.concatenate([p["F"][n][p["valid"]] for p in parts])
        print(f"   {n:5s}" + "".join(
            f"  {g[:8]}: {np.nanmedian(F[m]):5.1f}/{np.nanpercentile(F[m], 90):5.1f} "
            + "/".join(f"{100 * np.mean(F[m] > gate):.0f}" for gate in parts[0]["gates"])
            + "%" for g, m in groups))  # fmt: skip
    print("-- mean radial / tangential flow (px per frame) cam1 | cam2, EPE cam1 / cam2")
    print(f"   {'truth':22s}" + "".join(
        f" | {g[:8]:8s} {true[0, m].mean():+.3f}/{true[1, m].mean():+.3f} "
        f"{true[2, m].mean():+.3f}/{true[3, m].mean():+.3f}" for g, m in groups[:-1]))  # fmt: skip
    for n in parts[0]["est"]:
        est = np.concatenate([p["est"][n][:, p["valid"]] for p in parts], axis=1)
        e1, e2 = np.hypot(*(est[:2] - true[:2])), np.hypot(*(est[2:] - true[2:]))
        print(f"   {n:22s}" + "".join(
            f" | {g[:8]:8s} {est[0, m].mean():+.3f}/{est[1, m].mean():+.3f} "
            f"{est[2, m].mean():+.3f}/{est[3, m].mean():+.3f} "
            f"{e1[m].mean():.3f}/{e2[m].mean():.3f}" for g, m in groups[:-1])
            + f" | static EPE {e1[static].mean():.4f}/{e2[static].mean():.4f}"
            f" (median {np.median(e1[static]):.4f})")  # fmt: skip
    print(
        "-- mean flow vector error |mean est - mean true| / |mean true| (%) cam1 / cam2 "
        "(issue 9), static mean EPE cam1 / cam2"
    )
    print(f"   {'':22s}" + "".join(f" {g[:8]:>12s}" for g, _ in groups[:-1]))
    for n in parts[0]["est"]:
        est = np.concatenate([p["est"][n][:, p["valid"]] for p in parts], axis=1)
        e1, e2 = np.hypot(*(est[:2] - true[:2])), np.hypot(*(est[2:] - true[2:]))
        cells = []
        for _, m in groups[:-1]:
            err = [np.hypot(*(est[c : c + 2, m].mean(axis=1) - true[c : c + 2, m].mean(axis=1)))
                   / np.hypot(*true[c : c + 2, m].mean(axis=1)) for c in (0, 2)]  # fmt: skip
            cells.append(f" {100 * err[0]:5.1f}/{100 * err[1]:5.1f}")
        print(f"   {n:22s}" + "".join(cells)
              + f"  {e1[static].mean():.4f}/{e2[static].mean():.4f}")  # fmt: skip
    print(flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--frames", default="0,1,2", help="first frames of the pairs")
    parser.add_argument("--set", default="", help="config fields, e.g. pool_model=constant")
    parser.add_argument("--gates", default="20,5", help="F gates, the first the high one")
    parser.add_argument(
        "--dec-gates",
        default="20,10,5",
        help="gates of the decoupled model's test, the first the high one",
    )
    parser.add_argument("--edge-gate", type=float, default=10.0,
                        help="the gain's gate at pools on a range edge")  # fmt: skip
    parser.add_argument("--edge-share", type=float, default=0.25,
                        help="a pool is on a range edge when the range test drops more "
                             "than this share of its neighbours")  # fmt: skip
    args = parser.parse_args()
    args.gates = [float(g) for g in args.gates.split(",")]
    args.dec_gates = [float(g) for g in args.dec_gates.split(",")]

    from omniflow.cli.common import config_from_settings
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from validation.inputs import Inputs, camera_model
    from validation.scoring_derived import moving_objects

    config = config_from_settings(args.set) if args.set else OmniFlowConfig()
    seen: dict = {}
    capture(seen)
    for directory in args.datasets:
        ds = open_dataset(directory)
        camera = camera_model(ds.meta)
        inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
        args.movers = set(moving_objects(ds.meta))
        parts = []
        for t in (int(v) for v in args.frames.split(",")):
            parts.append(run_pair(ds, inputs, t, config, seen, args))
            parts[-1]["gates"] = sorted({*args.gates, *args.dec_gates, args.edge_gate})
        report(ds, directory, parts, set(moving_objects(ds.meta)), args.frames)


if __name__ == "__main__":
    main()
