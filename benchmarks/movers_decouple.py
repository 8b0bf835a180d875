"""Score the default configuration with ``decouple_tol`` (and other knobs) set.

The command behind docs/measurements.md, "Movers: decoupled radial flow"::

    python benchmarks/movers_decouple.py TOL DATASET OUT [omnivalidate options]
    python benchmarks/movers_decouple.py decouple_tol=20,flow_shading=8 DATASET OUT [...]

runs ``omnivalidate DATASET --out OUT --variants default`` with every
default OmniFlowConfig carrying ``decouple_tol=TOL`` ('none' for None; or
the NAME=VALUE fields given) and writes OUT/decouple.json: the share of
points switched to the decoupled model and the quantiles of the F statistic
(omniflow.solve.decoupled.model_fits).
"""

from __future__ import annotations

import inspect
import json
import sys
from pathlib import Path

import numpy as np

import omniflow.config as config
import omniflow.solve.decoupled as decoupled


def main(argv: list[str]) -> int:
    tol, dataset, out = argv[0], argv[1], argv[2]
    names = [p for p in inspect.signature(config.OmniFlowConfig.__init__).parameters][1:]
    defaults = list(config.OmniFlowConfig.__init__.__defaults__)
    pairs = [kv.split("=") for kv in tol.split(",")] if "=" in tol else [("decouple_tol", tol)]
    for name, value in pairs:
        defaults[names.index(name)] = None if value == "none" else float(value)
    config.OmniFlowConfig.__init__.__defaults__ = tuple(defaults)
    seen: list[np.ndarray] = []
    fits = decoupled.model_fits

    def recording(*args, **kw):
        fit = fits(*args, **kw)
        seen.append(fit["F"])
        return fit

    decoupled.model_fits = recording
    from validation.cli import main as omnivalidate

    rc = omnivalidate([dataset, "--out", out, "--variants", "default", *argv[3:]])
    F = np.concatenate(seen) if seen else np.zeros(0)
    F = F[np.isfinite(F)]
    t = defaults[names.index("decouple_tol")]
    stats = {
        "decouple_tol": t,
        "n": int(F.size),
        "switched_share": float(np.mean(F > t)) if t is not None and F.size else 0.0,
        "F_max": float(F.max()) if F.size else None,
        "F_quantiles": {q: float(np.quantile(F, q / 100)) for q in (50, 90, 99, 99.9)}
        if F.size
        else {},
    }
    Path(out, "decouple.json").write_text(json.dumps(stats, indent=1))
    print(json.dumps(stats))
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
