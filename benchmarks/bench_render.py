"""Speed and noise of the Mitsuba renderer and of the exact ground truth.

For a scene (default ``scenes/default.toml``) at its render settings
(512 x 512, direct light, 64 spp, Open Image Denoise by default), reports:

- seconds per stereo frame (both cameras) for the render and, separately,
  for the ground truth (median over ``--frames`` frames after one warm-up
  frame that includes JIT compilation), wall clock and process CPU time;
- the image noise at that spp: std of the difference of two renders of the
  same frame with different seeds, divided by sqrt 2, relative to the mean
  radiance (luminance, inside the rim);
- the departure of the rendered geometry from eq. (1): each pixel centre's
  float32 sensor ray traced through the Mitsuba scene, its hit's (r, h)
  put through eq. (1), compared with the pixel's h_i (max and RMS, pixels);
- with ``--candidates``, render settings side by side on frame 0 (seconds
  and CPU seconds per stereo frame: render, denoise, ground truth; the ratio
  of the total, and of the CPU seconds, to the first candidate's (the
  baseline), and the total's ratio times the baseline's idle-machine time;
  the residual against a converged path-traced reference (``--ref-depth``,
  default 8; two independent halves, their noise removed), cached in
  ``--ref-cache``, in % of the mean luminance over the common annulus; the
  error of the image gradient; the high-frequency energy kept; the mean
  luminance over the reference's; with ``--epe`` OpenCV DIS's end-point
  error against gt.flow);
- with ``--sizes``, the scene's render at other image sizes (time, noise);
- with ``--integrators``, the same render figures for other integrators;
- with ``--aperture N F D``, a thin lens of f-number N, focal length F and focus
  distance D (m; ``[optics]``): seconds per stereo frame as a ratio to the pinhole
  in the same run, and the spp at which the lens image's residual against a
  converged lens reference falls under 1 % of the mean luminance;
- with ``--updates``, moving objects re-posed in place through
  ``mi.traverse`` versus a new Mitsuba scene per frame (on a scene with
  moving objects, ``scenes/crossing.toml`` unless ``--scene`` has some).

The machine's load average is printed with the figures: on a shared machine
wall-clock times grow with the load while CPU times do not. Run::

    python benchmarks/bench_render.py
    python benchmarks/bench_render.py --frames 3 --integrators --updates --json out.json
    python benchmarks/bench_render.py --scene scenes/crossing.toml --set render.spp=4
    python benchmarks/bench_render.py --skip-default --candidates --epe --sizes 128 192 256
    python benchmarks/bench_render.py --skip-default --aperture 2.8 0.0056 0.2 \
        --set render.width=256 --set render.height=256
    python benchmarks/bench_render.py --variant cuda_ad_rgb --candidates   # with a GPU

``--variant cuda_ad_rgb`` on a machine without a CUDA device stops with one line
(exit 2).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from omniflow.io.imageio import atomic_write_text, to_grey
from omniflow.io.jsonio import json_text
from omnisim import render
from omnisim.groundtruth import ground_truth_frame
from omnisim.scene import load_scene, parse_override
from omnisim.sensor import ensure_mitsuba, make_sensor

ROOT = Path(__file__).resolve().parents[1]

INTEGRATORS = {
    "path, max_depth 3": {"type": "path", "max_depth": 3},
    "path, max_depth 2 (direct, MIS)": {"type": "path", "max_depth": 2},
    "direct (emitter + BSDF samples, MIS)": {"type": "direct"},
    "direct (emitter samples only)": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
}


def _clock():
    return time.perf_counter(), time.process_time()


def _since(t0):
    return time.perf_counter() - t0[0], time.process_time() - t0[1]


def _luma(img):
    return to_grey(img)


def time_frames(scene, frames: int) -> dict:
    """Render + ground truth of frames 0..frames (frame 0 is the warm-up)."""
    render.clear_cache()
    rows = []
    for f in range(frames + 1):
        t = _clock()
        tm: dict = {}
        imgs = {cam: render.render_camera(scene, f, cam, timings=tm) for cam in render.CAMERAS}
        r_wall, r_cpu = _since(t)
        t = _clock()
        ground_truth_frame(scene, f)
        g_wall, g_cpu = _since(t)
        rows.append((r_wall, r_cpu, g_wall, g_cpu, tm.get("denoise", 0.0)))
        print(
            f"  frame {f}: render {r_wall:.2f} s (cpu {r_cpu:.2f}; of which denoise "
            f"{tm.get('denoise', 0.0):.2f} s), "
            f"ground truth {g_wall:.3f} s (cpu {g_cpu:.3f})" + ("  [warm-up]" if f == 0 else ""),
            flush=True,
        )
    steady = rows[1:] or rows
    med = [statistics.median(col) for col in zip(*steady, strict=True)]
    return {
        "render_s": med[0],
        "render_cpu_s": med[1],
        "groundtruth_s": med[2],
        "groundtruth_cpu_s": med[3],
        "denoise_s": med[4],
        "first_frame_s": rows[0][0] + rows[0][2],
        "images": imgs,
    }


def noise(scene, frame: int = 0) -> dict:
    """Relative noise: std(I_a - I_b) / sqrt 2 / mean(I) over pixels inside the rim."""
    out = {}
    for cam in render.CAMERAS:
        unit = getattr(scene.rig, cam)
        a = _luma(render.render_camera(scene, frame, cam, seed=1001))
        b = _luma(render.render_camera(scene, frame, cam, seed=2002))
        x, y = unit.pixel_centres()
        inside = np.hypot(x - unit.x_c, y - unit.y_c) < unit.r_m - 1
        sigma = float(np.std((a - b)[inside]) / np.sqrt(2))
        out[cam] = {
            "sigma": sigma,
            "mean": float(a[inside].mean()),
            "relative": sigma / float(a[inside].mean()),
        }
    return out


def geometry_departure(scene, frame: int = 0) -> dict:
    """Eq. (1) residual of the float32 sensor rays traced through the Mitsuba scene."""
    mi = ensure_mitsuba()
    ms = render.get_mitsuba_scene(scene)
    fr = ms.frame(frame)
    inv = np.linalg.inv(fr.robot_pose)
    worst, sq, n = 0.0, 0.0, 0
    for cam in render.CAMERAS:
        unit = getattr(scene.rig, cam)
        sensor = make_sensor(unit, fr.robot_pose, spp=1)
        x, y = unit.pixel_centres()
        x, y = x.ravel(), y.ravel()
        ray, _ = sensor.sample_ray(
            mi.Float(0.0),
            mi.Float(0.5),
            mi.Point2f(mi.Float(x / unit.width), mi.Float(y / unit.height)),
            mi.Point2f(0.5, 0.5),
        )
        si = fr.scene.ray_intersect(ray)
        p = np.stack([np.array(c, dtype=np.float64) for c in si.p], axis=-1)
        q = p @ inv[:3, :3].T + inv[:3, 3]
        h_i = np.hypot(x - unit.x_c, y - unit.y_c)
        ok = np.array(si.is_valid()) & (h_i <= unit.r_m)
        err = np.abs(unit.image_radius(np.hypot(q[:, 0], q[:, 1]), q[:, 2]) - h_i)[ok]
        worst = max(worst, float(err.max()))
        sq += float((err**2).sum())
        n += len(err)
    return {"max_px": worst, "rms_px": (sq / max(n, 1)) ** 0.5, "pixels": n}


def integrators(scene) -> dict:
    mi = ensure_mitsuba()
    out = {}
    for name, desc in INTEGRATORS.items():
        render.clear_cache()
        ms = render.get_mitsuba_scene(scene)
        ms.integrator = mi.load_dict(desc)
        render.render_camera(scene, 0, "cam2")  # compile
        walls, cpus = [], []
        for k in range(2):
            t = _clock()
            for cam in render.CAMERAS:
                render.render_camera(scene, 0, cam, seed=10 + k)
            w, c = _since(t)
            walls.append(w)
            cpus.append(c)
        nz = noise(scene)
        rel = float(np.mean([v["relative"] for v in nz.values()]))
        mean = float(np.mean([v["mean"] for v in nz.values()]))
        out[name] = {
            "stereo_render_s": min(walls),
            "stereo_render_cpu_s": min(cpus),
            "relative_noise": rel,
            "mean_radiance": mean,
        }
        print(
            f"  {name:40s} {min(walls):6.2f} s (cpu {min(cpus):5.2f})  "
            f"noise {rel:.4f}  mean {mean:.4f}",
            flush=True,
        )
    render.clear_cache()
    return out


def updates(scene, frames: int) -> dict:
    """In-place re-posing (mi.traverse) versus rebuilding the scene, per new frame.

    Reports the scene update time, the next render's CPU time and how much of
    it was JIT compilation (Dr.Jit's kernel history), per camera render.
    """
    import drjit as dr

    if not any(getattr(o, "moving", False) for o in scene.objects):
        print("  (no moving objects in this scene: using scenes/crossing.toml)")
        scene = load_scene(
            ROOT / "scenes" / "crossing.toml",
            {
                "render.width": scene.render.width,
                "render.height": scene.render.height,
                "render.spp": scene.render.spp,
            },
        )
    out = {}
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    for mode in ("traverse", "rebuild"):
        render.clear_cache()
        ms = render.get_mitsuba_scene(scene)
        ms.update = mode
        prep, cpu, comp = [], [], []
        for f in range(frames + 2):
            t = _clock()
            ms.frame(f)
            prep.append(_since(t)[0])
            dr.kernel_history_clear()
            t = _clock()
            render.render_camera(scene, f, "cam2")
            cpu.append(_since(t)[1])
            hist = dr.kernel_history()
            comp.append(sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in hist))
        # frames 0 and 1 build the two slots; later frames re-pose or rebuild
        out[mode] = {
            "scene_update_s": statistics.median(prep[2:]),
            "render_cpu_s": statistics.median(cpu[2:]),
            "jit_compile_ms": statistics.median(comp[2:]),
        }
        print(
            f"  {mode:9s}: scene update {out[mode]['scene_update_s'] * 1e3:6.1f} ms, next render "
            f"cpu {out[mode]['render_cpu_s']:.2f} s of which JIT compilation "
            f"{out[mode]['jit_compile_ms']:.0f} ms (one camera)",
            flush=True,
        )
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    render.clear_cache()
    return out


# ----------------------------------------------------------------------------
# Candidates against a converged reference
# ----------------------------------------------------------------------------
#: Render settings compared by ``--candidates``: ``INTEGRATOR[/dN][/rrN][/gN]:SPP[+oidn]``
#: (``dN``: max_depth N; ``rrN``: Russian roulette from depth N; ``gN``: the denoiser's
#: guides at N spp). The first is the baseline the times are divided by.
CANDIDATES = (
    "direct:64+oidn",
    "path/d5:8+oidn",
    "path/d6/rr3:8+oidn",
    "path/d8/rr3:4+oidn",
    "path/d8/rr3/g16:4+oidn",
    "path/d8/rr3:8+oidn",
    "path/d8/rr3:16+oidn",
)
#: Samples per pixel of one reference pass (the reference is a mean of passes).
REF_PASS_SPP = 16
#: Seconds per stereo frame of the baseline (direct, 64 spp, Open Image Denoise) on the
#: idle 2-core machine (render, denoise and ground truth; docs/decisions/render_light.md):
#: a candidate's estimate is its time ratio to the baseline, measured in the same run,
#: times this.
BASELINE_IDLE_S = 3.9


def _spec(spec: str) -> dict:
    """Scene overrides and integrator extras of a candidate spec (see CANDIDATES)."""
    head, rest = spec.split(":")
    integrator, *opts = head.split("/")
    spp, _, den = rest.partition("+")
    out = {
        "overrides": {
            "render.integrator": integrator,
            "render.spp": int(spp),
            "render.denoise": den or "none",
        },
        "rr_depth": None,
        "guide_spp": None,
    }
    for opt in opts:
        if opt.startswith("rr"):
            out["rr_depth"] = int(opt[2:])
        elif opt.startswith("d"):
            out["overrides"]["render.max_depth"] = int(opt[1:])
        elif opt.startswith("g"):
            out["guide_spp"] = int(opt[1:])
        else:
            raise SystemExit(f"bench_render.py: candidate {spec!r}: unknown option {opt!r}")
    return out


def reference(scene, kind: str, half_spp: int, cache: Path, frame: int = 0, depth: int = 8) -> dict:
    """Two independent half references per camera, (H, W, 3) each, cached as .npy.

    ``kind`` "path" is the path tracer to ``depth`` (direct and indirect light);
    "direct" samples the emitters only (direct light). Each
    half is the mean of ``half_spp / REF_PASS_SPP`` renders of
    ``REF_PASS_SPP`` spp with their own seeds; the difference of the halves
    measures the noise left in their mean, which :func:`residual` removes.
    """
    mi = ensure_mitsuba()
    ms = render.get_mitsuba_scene(scene)
    fr = ms.frame(frame)
    integ = mi.load_dict(
        {
            "path": {"type": "path", "max_depth": int(depth), "hide_emitters": False},
            "direct": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        }[kind]
    )
    r = scene.render
    out: dict = {}
    for cam in render.CAMERAS:
        sensor = make_sensor(getattr(scene.rig, cam), fr.robot_pose, spp=REF_PASS_SPP)
        for half, base in (("A", 100000), ("B", 200000)):
            tag = f"path{depth}" if kind == "path" else kind
            name = f"{scene.name}_f{frame}_{r.width}_{tag}_{half_spp}_{cam}_{half}.npy"
            path = cache / name
            if not path.exists():
                t = time.perf_counter()
                acc = np.zeros((r.height, r.width, 3))
                passes = half_spp // REF_PASS_SPP
                for i in range(passes):
                    seed = base + i + (0 if cam == "cam1" else 50000)
                    acc += np.array(
                        mi.render(
                            fr.scene, sensor=sensor, integrator=integ, spp=REF_PASS_SPP, seed=seed
                        )
                    )
                cache.mkdir(parents=True, exist_ok=True)
                np.save(path, (acc / passes).astype(np.float32))
                print(f"  reference {name}: {time.perf_counter() - t:.0f} s", flush=True)
            out[cam, half] = np.load(path)
    return out


def _common(gt: dict) -> np.ndarray:
    """Pixels of the common annulus: valid, seen by the other camera, 1 px inside it."""
    from scipy import ndimage

    m = (gt["gt.valid"] > 0.5) & (gt["gt.stereo.valid"] > 0.5)
    return ndimage.binary_erosion(m, np.ones((3, 3)), border_value=0)


def residual(imgs: dict, ref: dict, masks: dict) -> dict:
    """Residual of ``imgs`` against the reference, % of the mean reference luminance.

    ``rms``: RMS of the luminance difference over the common annulus of both
    cameras, with the reference's own remaining noise removed in quadrature
    (E|x - (A+B)/2|^2 = E|x - truth|^2 + E|(A-B)/2|^2 for independent seeds).
    ``grad``: the same for the image gradient (np.gradient, both axes), as a
    % of the RMS reference gradient (its noise removed the same way): texture
    lost or added. ``texture``: the high-frequency energy kept, E|lap(x)|^2 over
    E|lap(truth)|^2 (``scipy.ndimage.laplace``; the truth's from the reference
    less its noise), in %: 100 keeps the texture, below blurs it, above adds noise.
    """
    from scipy import ndimage

    se = sg = nr = ng = gref = mean = hx = hr = hn = ysum = 0.0
    n = 0
    for cam, x in imgs.items():
        m = masks[cam]
        a, b = _luma(ref[cam, "A"]), _luma(ref[cam, "B"])
        r = (a + b) / 2
        half = (a - b) / 2
        y = _luma(x)
        d = y - r
        se += float((d[m] ** 2).sum())
        nr += float((half[m] ** 2).sum())
        gx = np.stack(np.gradient(d), -1)[m]
        gh = np.stack(np.gradient(half), -1)[m]
        gr = np.stack(np.gradient(r), -1)[m]
        sg += float((gx**2).sum())
        ng += float((gh**2).sum())
        gref += float((gr**2).sum())
        hx += float((ndimage.laplace(y)[m] ** 2).sum())
        hr += float((ndimage.laplace(r)[m] ** 2).sum())
        hn += float((ndimage.laplace(half)[m] ** 2).sum())
        mean += float(r[m].sum())
        ysum += float(y[m].sum())
        n += int(m.sum())
    mean_ratio = ysum / mean
    mean /= n
    return {
        "rms_pct": 100 * np.sqrt(max(se - nr, 0.0) / n) / mean,
        "grad_pct": 100 * np.sqrt(max(sg - ng, 0.0) / max(gref - ng, 1e-30)),
        "texture_pct": 100 * hx / max(hr - hn, 1e-30),
        "ref_noise_pct": 100 * np.sqrt(nr / n) / mean,
        "mean": mean,
        "mean_ratio": mean_ratio,
        "pixels": n,
    }


def dis_epe(scene, imgs0: dict, gts: dict, frame: int = 0) -> dict:
    """OpenCV DIS (medium) flow from frame to frame + 1 against gt.flow, common annulus.

    Images go to 8 bits through the same linear scale (frame's 99.5th
    percentile luminance -> 255). The figure is the mean end-point error (px).
    """
    import cv2

    out = {}
    for cam in render.CAMERAS:
        a = _luma(imgs0[cam])
        b = _luma(render.render_camera(scene, frame + 1, cam))
        scale = 255.0 / np.percentile(a[a > 0], 99.5)
        a8 = np.clip(a * scale, 0, 255).astype(np.uint8)
        b8 = np.clip(b * scale, 0, 255).astype(np.uint8)
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        flow = dis.calc(a8, b8, None)
        gt = gts[cam]
        m = _common(gt) & (gt["gt.flow.valid"] > 0.5)
        e = np.hypot(flow[..., 0] - gt["gt.flow.dx"], flow[..., 1] - gt["gt.flow.dy"])[m]
        out[cam] = float(e.mean())
    return out


def _render_candidate(sc, cand: dict, reps: int) -> tuple[dict, dict]:
    """Median seconds (render, denoise, ground truth, cpu) and the images of frame 0."""
    mi = ensure_mitsuba()
    render.clear_cache()
    ms = render.get_mitsuba_scene(sc)
    if cand["rr_depth"] is not None:
        ms.integrator = mi.load_dict(
            {
                "type": "path",
                "max_depth": int(sc.render.max_depth),
                "rr_depth": cand["rr_depth"],
                "hide_emitters": False,
            }
        )
    rows = []
    for k in range(reps + 1):  # the first is the warm-up (JIT compilation)
        tm: dict = {}
        c0 = time.process_time()
        imgs = {
            cam: render.render_camera(sc, 0, cam, timings=tm, guide_spp=cand["guide_spp"])
            for cam in render.CAMERAS
        }
        t = time.perf_counter()
        ground_truth_frame(sc, 0)
        tm["groundtruth"] = time.perf_counter() - t
        tm["cpu"] = time.process_time() - c0
        if k:
            rows.append(tm)
    med = {
        key: statistics.median(r.get(key, 0.0) for r in rows)
        for key in ("render", "denoise", "groundtruth", "cpu")
    }
    med["total"] = med["render"] + med["denoise"] + med["groundtruth"]
    return med, imgs


def candidates(
    path: str,
    overrides: dict,
    specs,
    reps: int,
    cache: Path,
    half_spp: dict,
    epe: bool,
    ref_depth: int = 8,
) -> dict:
    """Time and residual of each candidate render on frame 0 (see ``--candidates``).

    The first spec is the baseline: every time is also printed as a ratio to its
    time in the same run, and as an estimate on the idle machine (ratio x
    :data:`BASELINE_IDLE_S`). A ``half_spp`` of 0 skips that reference.
    """
    base = load_scene(path, overrides)
    print(f"  references (cached in {cache}):", flush=True)
    refs = {k: reference(base, k, n, cache, depth=ref_depth) for k, n in half_spp.items() if n > 0}
    gts = ground_truth_frame(base, 0)
    masks = {cam: _common(gts[cam]) for cam in render.CAMERAS}
    for k, ref in refs.items():
        res = residual({c: (ref[c, "A"] + ref[c, "B"]) / 2 for c in render.CAMERAS}, ref, masks)
        print(
            f"  reference {k}"
            + (f" (max_depth {ref_depth})" if k == "path" else "")
            + f": {2 * half_spp[k]} spp, remaining noise "
            f"{res['ref_noise_pct']:.2f} % of the mean {res['mean']:.4f} "
            f"({res['pixels']} pixels)",
            flush=True,
        )
    out: dict = {"ref_depth": ref_depth, "baseline": specs[0], "baseline_idle_s": BASELINE_IDLE_S}
    if "direct" in refs:
        res = residual(
            {c: (refs["direct"][c, "A"] + refs["direct"][c, "B"]) / 2 for c in render.CAMERAS},
            refs["path"],
            masks,
        )
        out["indirect_pct"] = res["rms_pct"]
        print(
            f"  converged direct vs converged path (the indirect light): {res['rms_pct']:.2f} %",
            flush=True,
        )
    print(
        f"  {'candidate':20s} {'render':>7s} {'denoise':>7s} {'gt':>6s} {'total':>6s} "
        f"{'cpu':>6s} {'ratio':>6s} {'cpu r.':>6s} {'est. s':>6s} | {'vs path':>7s} {'grad':>6s} "
        f"{'texture':>7s} {'mean':>6s}"
        + (f" | {'vs direct':>9s}" if "direct" in refs else "")
        + ("  | DIS EPE cam1/cam2" if epe else ""),
        flush=True,
    )
    base_total = base_cpu = None
    for spec in specs:
        cand = _spec(spec)
        sc = load_scene(path, {**overrides, **cand["overrides"]})
        med, imgs = _render_candidate(sc, cand, reps)
        if base_total is None:
            base_total, base_cpu = med["total"], med["cpu"]
        ratio = med["total"] / base_total
        cpu_ratio = med["cpu"] / base_cpu
        rp = residual(imgs, refs["path"], masks)
        row = {
            **med,
            "ratio": ratio,
            "cpu_ratio": cpu_ratio,
            "estimate_idle_s": ratio * BASELINE_IDLE_S,
            "vs_path": rp,
        }
        line = (
            f"  {spec:20s} {med['render']:7.2f} {med['denoise']:7.2f} "
            f"{med['groundtruth']:6.2f} {med['total']:6.2f} {med['cpu']:6.2f} {ratio:6.2f} "
            f"{cpu_ratio:6.2f} "
            f"{ratio * BASELINE_IDLE_S:6.2f} | {rp['rms_pct']:6.2f}% {rp['grad_pct']:5.1f}% "
            f"{rp['texture_pct']:6.1f}% {rp['mean_ratio']:6.3f}"
        )
        if "direct" in refs:
            rd = residual(imgs, refs["direct"], masks)
            row["vs_direct"] = rd
            line += f" | {rd['rms_pct']:8.2f}%"
        if epe:
            row["dis_epe"] = dis_epe(sc, imgs, gts)
            line += f"  | {row['dis_epe']['cam1']:.3f} / {row['dis_epe']['cam2']:.3f}"
        print(line + f"   (load {os.getloadavg()[0]:.1f})", flush=True)
        out[spec] = row
    render.clear_cache()
    return out


def sizes(path: str, overrides: dict, widths, reps: int) -> dict:
    """Seconds per stereo frame and two-seed noise of the scene's render at other sizes."""
    out = {}
    for w in widths:
        render.clear_cache()
        sc = load_scene(path, {**overrides, "render.width": w, "render.height": w})
        rows = []
        for k in range(reps + 1):
            tm: dict = {}
            c0 = time.process_time()
            for cam in render.CAMERAS:
                render.render_camera(sc, k, cam, timings=tm)
            t = time.perf_counter()
            ground_truth_frame(sc, k)
            tm["groundtruth"] = time.perf_counter() - t
            tm["cpu"] = time.process_time() - c0
            if k:
                rows.append(tm)
        med = {
            key: statistics.median(r.get(key, 0.0) for r in rows)
            for key in ("render", "denoise", "groundtruth")
        }
        cpu = statistics.median(r["cpu"] for r in rows)
        nz = noise(sc)
        rel = float(np.mean([v["relative"] for v in nz.values()]))
        total = sum(med.values())
        out[w] = {**med, "total": total, "cpu": cpu, "noise": rel}
        print(
            f"  {w:4d} px: render {med['render']:.2f} s, denoise {med['denoise']:.2f} s, "
            f"ground truth {med['groundtruth']:.2f} s = {total:.2f} s per stereo frame; "
            f"two-seed noise {100 * rel:.2f} % of the mean  (load {os.getloadavg()[0]:.1f})",
            flush=True,
        )
    render.clear_cache()
    return out


def _stereo_seconds(scene, reps: int, **kw) -> float:
    """Median wall seconds of a stereo render of frame 0 (after one warm-up)."""
    times = []
    for k in range(reps + 1):
        t = _clock()
        for cam in render.CAMERAS:
            render.render_camera(scene, 0, cam, **kw)
        if k:
            times.append(_since(t)[0])
    return statistics.median(times)


def aperture(path, overrides: dict, lens, reps: int, spps, ref_spp: int) -> dict:
    """A thin lens against the pinhole: time ratio, and the spp for a 1 % residual.

    The residual of a lens render at each spp (the scene's denoiser) is measured
    against the mean of two undenoised lens renders of ``ref_spp / 2`` each, the
    reference's own noise (a quarter of their squared difference) subtracted, in % of
    the mean luminance inside the rim, cam2, frame 0; the pinhole's the same way.
    """
    n, f, focus = lens
    keys = {"optics.f_number": n, "optics.focal_length": f, "optics.focus_distance": focus}
    pin = load_scene(path, overrides)
    lensed = load_scene(path, {**overrides, **keys})
    t_pin = _stereo_seconds(pin, reps)
    render.clear_cache()
    t_lens = _stereo_seconds(lensed, reps)
    print(
        f"  f/{n:g}, f = {1e3 * f:g} mm, focus {focus:g} m: {t_lens:.2f} s per stereo frame, "
        f"{t_lens / t_pin:.2f} x the pinhole's {t_pin:.2f} s  (load {os.getloadavg()[0]:.1f})",
        flush=True,
    )
    unit = lensed.rig.cam2
    x, y = unit.pixel_centres()
    inside = np.hypot(x - unit.x_c, y - unit.y_c) < unit.r_m - 1
    rows, needed = {}, {}
    for name, sc, extra in (("pinhole", pin, {}), ("lens", lensed, keys)):
        render.clear_cache()
        raw = load_scene(path, {**overrides, **extra, "render.denoise": "none"})
        a = _luma(render.render_camera(raw, 0, "cam2", spp=ref_spp // 2, seed=11))
        b = _luma(render.render_camera(raw, 0, "cam2", spp=ref_spp // 2, seed=12))
        ref, ref_var = (a + b) / 2, float(np.mean((a - b)[inside] ** 2)) / 4
        mean = float(ref[inside].mean())
        rows[name], needed[name] = {}, None
        render.clear_cache()
        for spp in spps:
            img = _luma(render.render_camera(sc, 0, "cam2", spp=spp, seed=3))
            mse = max(float(np.mean((img - ref)[inside] ** 2)) - ref_var, 0.0)
            rel = float(np.sqrt(mse)) / mean
            rows[name][spp] = rel
            if needed[name] is None and rel < 0.01:
                needed[name] = spp
            print(f"  {name:7s} {spp:5d} spp: residual {100 * rel:.2f} % of the mean", flush=True)
    render.clear_cache()
    return {
        "f_number": n,
        "focal_length": f,
        "focus_distance": focus,
        "pinhole_s": t_pin,
        "lens_s": t_lens,
        "ratio": t_lens / t_pin,
        "residual": rows,
        "spp_for_1pct": needed,
        "ref_spp": ref_spp,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "scenes" / "default.toml"))
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="scene override, e.g. render.spp=4 (repeatable)",
    )
    ap.add_argument("--frames", type=int, default=3, help="timed frames after the warm-up")
    ap.add_argument("--integrators", action="store_true", help="compare integrators")
    ap.add_argument("--updates", action="store_true", help="traverse update vs rebuild")
    ap.add_argument(
        "--candidates",
        nargs="*",
        metavar="SPEC",
        help="compare render settings against a converged reference: integrator:spp or "
        f"integrator:spp+oidn (no SPEC: {' '.join(CANDIDATES)})",
    )
    ap.add_argument("--reps", type=int, default=3, help="timed stereo frames per candidate")
    ap.add_argument(
        "--ref-spp",
        type=int,
        nargs=2,
        default=[512, 0],
        metavar=("PATH", "DIRECT"),
        help="spp of the path and the direct reference (two halves of half as many; "
        "0: no direct reference)",
    )
    ap.add_argument(
        "--ref-depth", type=int, default=8, help="max_depth of the path-traced reference"
    )
    ap.add_argument(
        "--ref-cache",
        type=Path,
        default=Path.home() / ".cache" / "omnisim_render_ref",
        help="reference cache",
    )
    ap.add_argument(
        "--variant",
        help="Mitsuba variant, e.g. cuda_ad_rgb (default: the scene's render.variant)",
    )
    ap.add_argument("--epe", action="store_true", help="with --candidates: DIS flow EPE too")
    ap.add_argument(
        "--sizes", type=int, nargs="*", metavar="PX", help="time and noise at these sizes too"
    )
    ap.add_argument(
        "--skip-default", action="store_true", help="skip the scene's own timing and noise"
    )
    ap.add_argument(
        "--aperture",
        type=float,
        nargs=3,
        metavar=("N", "F", "D"),
        help="thin lens f-number, focal length (m), focus distance (m) vs the pinhole",
    )
    ap.add_argument(
        "--aperture-spp",
        type=int,
        nargs="*",
        default=[4, 16, 64, 256],
        help="spp to try for the lens's 1 %% residual",
    )
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args(argv)

    overrides = dict(parse_override(s) for s in args.set)
    if args.variant:
        overrides["render.variant"] = args.variant
    scene = load_scene(args.scene, overrides)
    try:
        mi = ensure_mitsuba(scene.render.variant)
    except ImportError as exc:  # Dr.Jit cannot start this backend here (no CUDA device)
        msg = " ".join(str(exc).split())[:160]
        print(
            f"bench_render.py: variant {scene.render.variant!r}: Mitsuba cannot use it on "
            f"this machine ({msg}); expected a variant that works here, e.g. llvm_ad_rgb",
            file=sys.stderr,
        )
        return 2
    r = scene.render
    print(
        f"scene {scene.name}: {r.width}x{r.height}, {r.spp} spp, integrator {r.integrator} "
        f"(max_depth {r.max_depth}), Mitsuba {mi.__version__} {mi.variant()}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    res: dict = {
        "scene": str(args.scene),
        "width": r.width,
        "height": r.height,
        "spp": r.spp,
        "integrator": r.integrator,
        "max_depth": r.max_depth,
        "mitsuba": mi.__version__,
        "variant": mi.variant(),
        "cpus": os.cpu_count(),
        "machine": platform.processor() or platform.machine(),
    }
    if not args.skip_default:
        print("per stereo frame (both cameras):")
        t = time_frames(scene, args.frames)
        t.pop("images")
        res.update(t)
        total = t["render_s"] + t["groundtruth_s"]
        print(
            f"render {t['render_s']:.2f} s (cpu {t['render_cpu_s']:.2f}), ground truth "
            f"{t['groundtruth_s']:.3f} s (cpu {t['groundtruth_cpu_s']:.3f}) = "
            f"{100 * t['groundtruth_s'] / total:.1f} % of {total:.2f} s per frame "
            f"(target <= 4 s, ground truth < 10 %)"
        )
        nz = noise(scene)
        res["noise"] = nz
        for cam, v in nz.items():
            print(
                f"noise {cam} at {r.spp} spp: sigma {v['sigma']:.5f} on mean {v['mean']:.4f} "
                f"= {100 * v['relative']:.2f} % of the mean radiance"
            )
        geo = geometry_departure(scene)
        res["eq1_departure"] = geo
        print(
            f"rendered geometry vs eq. (1) at the pixel centres: max {geo['max_px']:.2e} px, "
            f"rms {geo['rms_px']:.2e} px over {geo['pixels']} pixels (target < 0.02 px)"
        )
    if args.sizes:
        print(f"sizes, scene render settings ({r.integrator}, {r.spp} spp, denoise {r.denoise}):")
        res["sizes"] = sizes(args.scene, overrides, args.sizes, args.reps)
    if args.candidates is not None:
        print(
            "candidates, frame 0, seconds per stereo frame (median of --reps), residual "
            "vs converged references (% of the mean luminance, common annulus):"
        )
        res["candidates"] = candidates(
            args.scene,
            overrides,
            args.candidates or CANDIDATES,
            args.reps,
            args.ref_cache,
            {"path": args.ref_spp[0] // 2, "direct": args.ref_spp[1] // 2},
            args.epe,
            ref_depth=args.ref_depth,
        )
    if args.aperture:
        print("thin lens vs pinhole (frame 0):")
        res["aperture"] = aperture(
            args.scene, overrides, args.aperture, args.reps, args.aperture_spp, args.ref_spp[1]
        )
    if args.integrators:
        print("integrators (stereo render at frame 0, best of 2):")
        res["integrators"] = integrators(scene)
    if args.updates:
        print("moving objects, per new frame:")
        res["updates"] = updates(scene, args.frames)
    res["load_average_end"] = os.getloadavg()[0]
    print(f"load average at the end {res['load_average_end']:.2f}")
    if args.json:
        atomic_write_text(args.json, json_text(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
