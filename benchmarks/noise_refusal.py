"""Noise-unit tests of the robust matcher's answers, scored against the truth.

For each dataset and frame pair, runs :func:`omniflow.pipeline.estimate` (the default
preset, on the images ``omnivalidate`` scores: the camera model applied to the radiance)
and, at each stereo match it answers with, rebuilds the matcher's polar tables (the fit
at the matching band, the tangential blur; :mod:`omniflow.matching.radial`) and the
same tables of one draw of unit white pixel noise passed through the same steps, which
gives each table sample's noise variance per unit pixel noise (``share``). With the
camera's noise sigma^2(I) = a I + b (:func:`omnisim.camera_noise.grey_noise_level`):

- ``1-rho``: the 1 - NCC a true match would have from the noise alone,
  rho = S / sqrt((S + N_1)(S + N_2)) (S the profiles' signal variance, N their noise),
  against the matches' own 1 - NCC;
- ``grad z``: |df1/dh_1| at the edge over the noise sd of that derivative; the rows
  ``z >= 3`` and ``z >= 5`` refuse the matches below (a gradient threshold in noise units);
- ``halves``: the profile's inner and outer halves matched on their own (+-6 columns of
  the match); the rows ``halves <= 1 px`` and ``<= 2 px`` refuse a match whose halves
  disagree by more (or by more than 3 of their noise-predicted sds, if larger): a
  profile spanning two depths or an alias.

With ``--closed-form``: the same on closed-form walls (omnisim.synthetic, 256 px, the
paper rig, white noise of sigma 0.01 whose level is given): a far striped wall (6 and
8 m), a hard-edged checker (odd harmonics to the 7th, squares of 0.1 m at 2 m and 0.05 m
at 3 m) and horizontal gratings (0.1 m at 3 m, 0.15 m at 2 m), the truth traced.

Each row: the answers kept and the stereo outliers (|h2 - gt.stereo.h_other| > 1 px)
among them. The long pass's profile is used for every match (the short pass's matches
too). Run (about a minute per 512 px scene of 4 frames)::

    python3 -m benchmarks.noise_refusal DATASET [DATASET ...]
    python3 -m benchmarks.noise_refusal --closed-form

The figures are in docs/decisions/noise_thresholds.md.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

TRUTH = ("gt.valid", "gt.object", "gt.stereo.valid", "gt.stereo.h_other")


def _grid(fit, unit, band):
    from omniflow.fit.series import Frame, truncate

    return Frame(truncate(fit, band), unit).f


def _white_grid(unit, cfg):
    from omniflow.fit.series import fill_outside_rim, fit_band
    from omniflow.paper.dct import fit_dct

    img = np.random.default_rng(20261207).standard_normal((unit.height, unit.width))
    img = fill_outside_rim(img.astype(np.float32), unit)
    return _grid(fit_dct(img, band=fit_band(cfg)), unit, cfg.band)


def _tables(grid, maps, blur, step):
    from omniflow.matching.tables import blur_lines, polar_table, radial_derivative

    t = blur_lines(polar_table(grid, maps), blur)
    return np.asarray(t, np.float64), np.asarray(radial_derivative(t, step), np.float64)


def _lin(table, k, cols):
    c0 = np.clip(np.floor(cols).astype(np.int64), 0, table.shape[1] - 2)
    f = cols - c0
    kk = np.broadcast_to(k.reshape(k.shape + (1,) * (cols.ndim - k.ndim)), cols.shape)
    return table[kk, c0] * (1.0 - f) + table[kk, c0 + 1] * f


def _unit_ncc(a, axis=-1):
    a = a - a.mean(axis=axis, keepdims=True)
    return a / np.maximum(np.linalg.norm(a, axis=axis, keepdims=True), 1e-30)


def half_disparities(t1, t2, k, c1, c2, offs, reach=6):
    """Each half of the image-1 profile matched on its own within +-``reach`` columns
    of the match: its disparity (sub-pixel, columns; parabola through the NCC)."""
    base = np.rint(c2 - c1).astype(np.int64)
    dd = np.arange(-reach - 1, reach + 2)
    r = np.arange(k.size)
    out = []
    for half in (offs <= 0, offs >= 0):
        o = offs[half]
        a = _unit_ncc(t1[k[:, None], c1[:, None] + o[None, :]])
        cc = c1[:, None, None] + base[:, None, None] + dd[None, :, None] + o[None, None, :]
        q = _unit_ncc(t2[k[:, None, None], np.clip(cc, 0, t2.shape[1] - 1)])
        curve = np.einsum("nl,ndl->nd", a, q)
        i = np.argmax(curve[:, 1:-1], axis=1) + 1
        y0, y1, y2 = curve[r, i - 1], curve[r, i], curve[r, i + 1]
        den = y0 - 2 * y1 + y2
        off = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
        out.append(base + dd[i] + np.clip(off, -0.5, 0.5))
    return out[0], out[1]


def match_figures(res, g1, g2, rig, cfg, levels) -> dict[str, np.ndarray]:
    """Per answered match: 1 - NCC, 1 - rho, grad z, halves' disagreement, sigma_d."""
    from omniflow.fit.series import fit_band, unit_fits, unit_frames
    from omniflow.matching.tables import polar_maps

    c = res.columns
    cam1, cam2 = rig.cam1, rig.cam2
    n_theta, h_step, h_min = cfg.n_theta, cfg.search.h_step, cfg.search.h_min
    patch = cam1.r_m / 8.0 if cfg.patch_radius is None else cfg.patch_radius
    step = patch / 16.0 if cfg.matching.profile_step is None else cfg.matching.profile_step
    stride = max(1, round(step / h_step))
    w = int(np.ceil(patch / (h_step * stride)))
    pad = w * stride + 10
    scale2 = cam2.v / cam1.v
    h_top = min(cam1.r_m - cfg.search.rim_margin, (cam2.r_m - cfg.search.rim_margin) / scale2)
    h0 = h_min - pad * h_step
    n_cols = int(np.floor((h_top - h_min) / h_step)) + 1 + 2 * pad
    maps = (
        polar_maps(cam1, n_theta, h0, h_step, n_cols),
        polar_maps(cam2, n_theta, scale2 * h0, scale2 * h_step, n_cols),
    )
    blur = cfg.matching.tangential_blur * n_theta / (2.0 * np.pi)
    tabs, shares = [], []
    for frames, unit, m, s in ((g1, cam1, maps[0], 1.0), (g2, cam2, maps[1], scale2)):
        fits = unit_fits(frames, 0, unit, cfg, "frames", fit_band(cfg))
        tabs.append(
            _tables(unit_frames(fits, unit, cfg, cfg.flow_band or 0.5)["a"].f, m, blur, s * h_step)
        )
        wt, wd = _tables(_white_grid(unit, cfg), m, blur, s * h_step)
        shares.append((np.mean(wt**2, axis=0), np.mean(wd**2, axis=0)))
    (t1, fh1), (t2, _) = tabs
    k = np.rint((np.asarray(c["theta"]) + np.pi) * n_theta / (2 * np.pi) - 0.5).astype(np.int64)
    k %= n_theta
    c1 = np.rint((np.asarray(c["h1"]) - h0) / h_step).astype(np.int64)
    c2 = (np.asarray(c["h2"]) / scale2 - h0) / h_step
    offs = stride * np.arange(-w, w + 1)
    p1 = t1[k[:, None], c1[:, None] + offs[None, :]]
    p2 = _lin(t2, k, c2[:, None] + offs[None, :])
    s1 = np.asarray(levels[0].sigma_at(np.clip(p1.mean(axis=1), 0, None)), np.float64)
    s2 = np.asarray(levels[1].sigma_at(np.clip(p2.mean(axis=1), 0, None)), np.float64)
    n1 = np.mean(shares[0][0][c1[:, None] + offs[None, :]], axis=1) * s1**2
    cols2 = np.clip(np.rint(c2[:, None] + offs[None, :]).astype(np.int64), 0, n_cols - 1)
    n2 = np.mean(shares[1][0][cols2], axis=1) * s2**2
    S = np.sqrt(np.maximum(p1.var(axis=1) - n1, 0) * np.maximum(p2.var(axis=1) - n2, 0))
    rho = S / np.sqrt(np.maximum((S + n1) * (S + n2), 1e-300))
    grad_z = np.abs(fh1[k, c1]) / np.sqrt(np.maximum(shares[0][1][c1] * s1**2, 1e-300))
    dp = 0.5 * (
        t1[k[:, None], c1[:, None] + offs[None, :] + 1]
        - t1[k[:, None], c1[:, None] + offs[None, :] - 1]
    )
    sigma_d = np.sqrt((n1 + n2) / np.maximum(np.sum(dp * dp, axis=1), 1e-300))
    d_in, d_out = half_disparities(t1, t2, k, c1, c2, offs)
    return {
        "one_minus_ncc": 1.0 - np.sum(_unit_ncc(p1) * _unit_ncc(p2), axis=1),
        "one_minus_rho": 1.0 - rho,
        "grad_z": grad_z,
        "sigma_d": sigma_d,
        "halves": np.abs(d_in - d_out) * h_step,
    }


RULES = {
    "all answers": lambda f: np.ones(f["grad_z"].size, bool),
    "grad z >= 3": lambda f: f["grad_z"] >= 3.0,
    "grad z >= 5": lambda f: f["grad_z"] >= 5.0,
    "halves <= 1 px": lambda f: f["halves"] <= np.maximum(1.0, 6.0 * f["sigma_d"]),
    "halves <= 2 px": lambda f: f["halves"] <= np.maximum(2.0, 6.0 * f["sigma_d"]),
}


def score_dataset(directory: str) -> dict:
    """Per rule: answers kept (per frame) and their stereo outliers, over the pairs."""
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from omnisim.camera_noise import grey_noise_level
    from validation.inputs import Inputs, camera_model
    from validation.sampling import sample_truth

    ds = open_dataset(directory)
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    level = grey_noise_level(inputs.camera)
    cfg = OmniFlowConfig()
    frames = ds.frames_done()
    kept = {r: 0 for r in RULES}
    wrong = {r: 0 for r in RULES}
    judged = {r: 0 for r in RULES}
    noise, model = [], []
    for t in range(len(frames) - 1):
        g1 = [inputs.grey(frames[i], "cam1") for i in (t, t + 1)]
        g2 = [inputs.grey(frames[i], "cam2") for i in (t, t + 1)]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = estimate(g1, g2, ds.rig, cfg)
        if len(res.columns["x"]) == 0:
            continue
        f = match_figures(res, g1, g2, ds.rig, cfg, (level, level))
        truth = {k: v for k, v in ds.read_frame(frames[t], "cam1").items() if k in TRUTH}
        tr = sample_truth(truth, res.columns["x"], res.columns["y"], channels=TRUTH)
        has = tr["bilinear_ok"] & (tr["gt.stereo.valid"] > 0.5)
        bad = ~(np.abs(np.asarray(res.columns["h2"]) - tr["gt.stereo.h_other"]) <= 1.0)
        noise.append(f["one_minus_rho"])
        model.append(f["one_minus_ncc"])
        for name, rule in RULES.items():
            keep = rule(f)
            kept[name] += int(keep.sum())
            judged[name] += int((keep & has).sum())
            wrong[name] += int((keep & has & bad).sum())
    pairs = max(len(frames) - 1, 1)
    return {
        "dataset": Path(directory).name,
        "rules": {
            r: (kept[r] / pairs, wrong[r] / judged[r] if judged[r] else float("nan")) for r in RULES
        },
        "noise_1_minus_rho": float(np.median(np.concatenate(noise))) if noise else float("nan"),
        "own_1_minus_ncc": float(np.median(np.concatenate(model))) if model else float("nan"),
    }


def checker(radius: float, size: float, contrast: float = 0.4, harmonics: int = 4):
    """A hard-edged checker of ``size`` m squares on a wall of ``radius`` m: the product of
    two square waves, each its odd harmonics up to 2 ``harmonics`` - 1 (a product of
    sines is two sines: sin A sin B = [sin(A - B + pi/2) + sin(A + B - pi/2)] / 2)."""
    from omnisim.synthetic import Texture

    circ = 2 * np.pi * radius
    fu0, fv0 = max(1, round(circ / (2 * size))) / circ, 1 / (2 * size)
    fu, fv, amp, phase = [], [], [], []
    for i in range(harmonics):
        for j in range(harmonics):
            m, n = 2 * i + 1, 2 * j + 1
            fu += [m * fu0, m * fu0]
            fv += [-n * fv0, n * fv0]
            amp += [contrast / (2 * m * n)] * 2
            phase += [np.pi / 2, -np.pi / 2]
    return Texture(
        fu=np.array(fu), fv=np.array(fv), amp=np.array(amp), phase=np.array(phase), mean=0.5
    )


def closed_form() -> list[tuple[str, dict]]:
    """Per closed-form wall: per rule, answers kept and the wrong ones among them."""
    from omniflow.config import OmniFlowConfig
    from omniflow.fit.noise import NoiseLevel
    from omniflow.pipeline import estimate
    from omnisim.synthetic import Cylinder, SyntheticScene, Texture
    from tests.helpers.scenes import paper_rig, true_h_other, wall_scene

    rig, sigma, cfg = paper_rig(), 0.01, OmniFlowConfig()
    level = NoiseLevel(0.0, sigma**2)

    def wall(radius, texture):
        return SyntheticScene(rig=rig, bodies=(Cylinder(radius=radius, id=1, texture=texture),))

    scenes = {
        "striped wall 8 m": wall_scene(rig, radius=8.0, seed=3),
        "striped wall 6 m": wall_scene(rig, radius=6.0, seed=4),
        "checker 0.1 m at 2 m": wall(2.0, checker(2.0, 0.1)),
        "checker 0.05 m at 3 m": wall(3.0, checker(3.0, 0.05)),
        "grating 0.1 m at 3 m": wall(
            3.0, Texture.periodic(5, period=0.1, detail=0.1, period_u=2 * np.pi * 3.0)
        ),
        "grating 0.15 m at 2 m": wall(
            2.0, Texture.periodic(5, period=0.15, detail=0.3, period_u=2 * np.pi * 2.0)
        ),
    }
    out = []
    for name, sc in scenes.items():
        g1, g2 = (
            [sc.render(cam, t, dtype=np.float32, noise=sigma, seed=1 + t) for t in (0, 1)]
            for cam in ("cam1", "cam2")
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = estimate(g1, g2, rig, cfg)
        row = {}
        if len(res.columns["x"]):
            f = match_figures(res, g1, g2, rig, cfg, (level, level))
            h2t, _ = true_h_other(
                sc, np.asarray(res.columns["h1"]), np.asarray(res.columns["theta"])
            )
            bad = ~(np.abs(np.asarray(res.columns["h2"]) - h2t) <= 1.0)
            row = {r: (int(rule(f).sum()), int((rule(f) & bad).sum())) for r, rule in RULES.items()}
        out.append((name, row))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("datasets", nargs="*")
    p.add_argument("--closed-form", action="store_true", help="the closed-form walls")
    args = p.parse_args(argv)
    names = list(RULES)
    if args.closed_form:
        print("| wall | " + " | ".join(f"{n}: matches, wrong" for n in names) + " |")
        print("|---|" + "---|" * len(names))
        for name, row in closed_form():
            cells = [f"{row[n][0]}, {row[n][1]}" if row else "0, 0" for n in names]
            print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
        return 0
    print(
        "| dataset | median 1 - NCC (own / noise alone) | "
        + " | ".join(f"{n}: pts/frame, outliers" for n in names)
        + " |"
    )
    print("|---|---|" + "---|" * len(names))
    for d in args.datasets:
        s = score_dataset(d)
        cells = [f"{s['rules'][n][0]:.0f}, {100 * s['rules'][n][1]:.1f} %" for n in names]
        print(
            f"| {s['dataset']} | {s['own_1_minus_ncc']:.1e} / {s['noise_1_minus_rho']:.1e} | "
            + " | ".join(cells)
            + " |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
