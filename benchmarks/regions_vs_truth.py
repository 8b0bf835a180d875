"""The ``omniflow`` command's regions on rendered datasets against their ground truth.

For each dataset and frame K, runs ``omniflow --dataset DIR --frame K
--auto-regions --region NAME:object:NAME`` (one object region per mover) and
prints, per region of ``regions.csv``: its points and which ground-truth
objects they lie on, and each figure against the truth at the same points
(estimate/truth): mean flow dx, dy, dh1_dt (the ground truth's flow channels
at the points' pixels), the centroid's dr/dt, time to contact (frames and
seconds), bearing and home-in heading (``omniflow.applications.regions.summarise`` of the
ground truth's r and theta at the points with the mover's known velocity: the
scenes' robots stand still with yaw 0, so a mover's world velocity is its
velocity relative to the rig), and for automatic groups their median own
velocity. Run::

    python benchmarks/regions_vs_truth.py                      # /work/data crossing, approach
    python benchmarks/regions_vs_truth.py --root DIR --frames 0 1 2
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from omniflow.applications.regions import summarise
from omniflow.io.dataset import open_dataset

#: Movers of each scene and their velocity in m/frame (world = rig frame: robot static,
#: yaw 0), from scenes/*.toml: velocity x frame_interval 0.05 s.
MOVERS = {
    "crossing": {"crosser": (0.015, 0.0), "pillar": (-0.010, 0.0)},
    "approach": {"incoming": (-0.015, 0.0)},
}


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    data = np.genfromtxt(path, delimiter=",", names=True, skip_header=1)
    data = np.atleast_1d(data)
    return {name: np.asarray(data[name], float) for name in data.dtype.names}


def _at(channels, key, x, y):
    """A ground-truth channel at the pixels the points lie in."""
    return channels[key][np.floor(y).astype(int), np.floor(x).astype(int)]


def run(root: Path, scene: str, k: int, work: Path) -> list[str]:
    ds = open_dataset(root / scene)
    movers = MOVERS[scene]
    ids = {name: i for i, name in ds.objects.items()}
    out = work / f"{scene}{k}"
    args = ["omniflow", "--dataset", str(ds.dir), "--frame", str(k), "--out", str(out)]
    args += ["--auto-regions", "--no-pictures"]
    for name in movers:
        args += ["--region", f"{name}:object:{name}"]
    proc = subprocess.run(args, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(proc.stderr)
    cols = _read_csv(out / "flow.csv")
    with open(out / "regions.csv") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    channels = ds.read_frame(k, "cam1")
    obj = _at(channels, "gt.object", cols["x"], cols["y"])
    lines = []
    for row in rows:
        name, n = row["name"], int(row["points"])
        if n == 0:
            lines.append(f"{scene} K={k} {name}: 0 points")
            continue
        if row["kind"] == "auto":
            member = cols["auto_region"] == int(name[4:])
        else:
            member = obj == ids[name]
        ids_on, counts = np.unique(obj[member], return_counts=True)
        on = {ds.objects.get(int(i), "none"): int(c) for i, c in zip(ids_on, counts, strict=True)}
        x, y = cols["x"][member], cols["y"][member]
        th, r = _at(channels, "gt.theta", x, y), _at(channels, "gt.r", x, y)
        vx, vy = movers.get(max(on, key=on.get), (0.0, 0.0))
        truth = {
            "theta": th,
            "r": r,
            "dr_dt": vx * np.cos(th) + vy * np.sin(th),
            "dtheta_dt": (-vx * np.sin(th) + vy * np.cos(th)) / r,
            "dh1_dt": _at(channels, "gt.flow.dh", x, y),
            "dx": _at(channels, "gt.flow.dx", x, y),
            "dy": _at(channels, "gt.flow.dy", x, y),
        }
        t = summarise("truth", "", "", truth, np.ones(x.size, bool),
                      frame_interval=ds.frame_interval)  # fmt: skip

        def f(key, row=row):
            return float(row[key]) if row[key] else float("inf")

        lines.append(
            f"{scene} K={k} {name}: {n} points on {on}; dx {f('dx'):+.3f}/{t['dx']:+.3f}, "
            f"dy {f('dy'):+.3f}/{t['dy']:+.3f}, dh1_dt {f('dh1_dt'):+.3f}/{t['dh1_dt']:+.3f} px; "
            f"dr/dt {1e3 * f('dr_dt'):+.2f}/{1e3 * t['dr_dt']:+.2f} mm/frame; "
            f"TTC {f('time_to_contact_frames'):.1f}/{t['time_to_contact_frames']:.1f} frames "
            f"({f('time_to_contact_s'):.2f}/{t['time_to_contact_s']:.2f} s); "
            f"bearing {f('bearing_deg'):+.2f}/{t['bearing_deg']:+.2f}, "
            f"home-in {f('steer_home_in_deg'):+.2f}/{t['steer_home_in_deg']:+.2f} deg"
            + (f"; {row['spec']}" if row["kind"] == "auto" else "")
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--root", type=Path, default=Path("/work/data"))
    parser.add_argument("--scenes", nargs="+", default=list(MOVERS), choices=list(MOVERS))
    parser.add_argument("--frames", nargs="+", type=int, default=[0, 1, 2])
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as work:
        for scene in args.scenes:
            for k in args.frames:
                print("\n".join(run(args.root, scene, k, Path(work))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
