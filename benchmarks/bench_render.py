"""Speed and noise of the Mitsuba renderer and of the exact ground truth.

For a scene (default ``scenes/default.toml``) at its resolution and spp
(512 x 512, 16 spp by default), reports:

- seconds per stereo frame (both cameras) for the render and, separately,
  for the ground truth (median over ``--frames`` frames after one warm-up
  frame that includes JIT compilation), wall clock and process CPU time;
- the image noise at that spp: std of the difference of two renders of the
  same frame with different seeds, divided by sqrt 2, relative to the mean
  radiance (luminance, inside the rim);
- the departure of the rendered geometry from eq. (1): each pixel centre's
  float32 sensor ray traced through the Mitsuba scene, its hit's (r, h)
  put through eq. (1), compared with the pixel's h_i (max and RMS, pixels);
- with ``--integrators``, the same render figures for other integrators;
- with ``--updates``, moving objects re-posed in place through
  ``mi.traverse`` versus a new Mitsuba scene per frame (on a scene with
  moving objects, ``scenes/crossing.toml`` unless ``--scene`` has some).

The machine's load average is printed with the figures: on a shared machine
wall-clock times grow with the load while CPU times do not. Run::

    python benchmarks/bench_render.py
    python benchmarks/bench_render.py --frames 3 --integrators --updates --json out.json
    python benchmarks/bench_render.py --scene scenes/crossing.toml --set render.spp=4
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from omniflow.conventions import LUMA_WEIGHTS  # noqa: E402
from omnisim import render  # noqa: E402
from omnisim.groundtruth import ground_truth_frame  # noqa: E402
from omnisim.scene import load_scene, parse_override  # noqa: E402
from omnisim.sensor import ensure_mitsuba, make_sensor  # noqa: E402

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
    return img @ np.asarray(LUMA_WEIGHTS, dtype=np.float32)


def time_frames(scene, frames: int) -> dict:
    """Render + ground truth of frames 0..frames (frame 0 is the warm-up)."""
    render.clear_cache()
    rows = []
    for f in range(frames + 1):
        t = _clock()
        imgs = {cam: render.render_camera(scene, f, cam) for cam in render.CAMERAS}
        r_wall, r_cpu = _since(t)
        t = _clock()
        ground_truth_frame(scene, f)
        g_wall, g_cpu = _since(t)
        rows.append((r_wall, r_cpu, g_wall, g_cpu))
        print(
            f"  frame {f}: render {r_wall:.2f} s (cpu {r_cpu:.2f}), "
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
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args(argv)

    overrides = dict(parse_override(s) for s in args.set)
    scene = load_scene(args.scene, overrides)
    mi = ensure_mitsuba(scene.render.variant)
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
    if args.integrators:
        print("integrators (stereo render at frame 0, best of 2):")
        res["integrators"] = integrators(scene)
    if args.updates:
        print("moving objects, per new frame:")
        res["updates"] = updates(scene, args.frames)
    res["load_average_end"] = os.getloadavg()[0]
    print(f"load average at the end {res['load_average_end']:.2f}")
    if args.json:
        tmp = args.json.with_suffix(args.json.suffix + ".partial")
        tmp.write_text(json.dumps(res, indent=2) + "\n")
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
