"""Each mover's mean flow per omniflow row of omnivalidate reports, against the truth.

For every omniflow row of each ``REPORT/summary.json`` and every moving object, per
camera: scored points, mean radial (dh) and tangential (h dtheta) flow, estimated /
true (px per frame), and the relative error of the mean flow vector,
``|mean est - mean true| / |mean true|`` (issue 9's "mean flow within 10 % of its true
image motion"), plus each camera's mean / median EPE and radial gain. Usage::

    python benchmarks/mover_table.py REPORT [REPORT ...]
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path


def rows(report: str) -> list[str]:
    s = json.loads((Path(report) / "summary.json").read_text())
    movers = set(s["dataset"].get("moving_objects") or [])
    out = [f"== {s['dataset']['scene']} ({report})"]
    for m in s["methods"]:
        if not m["name"].startswith("omniflow") or "flow" not in m:
            continue
        head = []
        for cam in ("cam1", "cam2"):
            a = m["flow"][cam]["all"]
            head.append(f"{cam} EPE {a['epe']['mean']:.4f}/{a['epe']['median']:.4f} "
                        f"gain_r {a['radial']['gain']:.2f}")  # fmt: skip
        out.append(f"  {m['name']}\n    " + "  ".join(head))
        for cam in ("cam1", "cam2"):
            for name, o in m["flow"][cam]["objects"].items():
                r, t = o.get("radial", {}), o.get("tangential", {})
                if not (o.get("id") in movers or name in movers) or r.get("mean_est") is None:
                    continue
                err = math.hypot(r["mean_est"] - r["mean_true"], t["mean_est"] - t["mean_true"])
                rel = err / math.hypot(r["mean_true"], t["mean_true"])
                out.append(f"    {cam} {name:8s} n {o['n']:4d}  dh {r['mean_est']:+.3f} / "
                           f"{r['mean_true']:+.3f}  h dtheta {t['mean_est']:+.3f} / "
                           f"{t['mean_true']:+.3f}  vector error {100 * rel:5.1f} %")  # fmt: skip
    return out


if __name__ == "__main__":
    for report in sys.argv[1:]:
        print("\n".join(rows(report)))
