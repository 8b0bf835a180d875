"""sweep.png: each metric of ``omnivalidate sweep`` against the swept value, a line per method."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .report_figures import save

__all__ = ["METRICS", "sweep_plot"]

#: What sweep.png draws, with its axis label (suite protocol names, docs/suite.md).
METRICS = {
    "1px": "1px: pixels with EPE > 1 px (dense)",
    "epe": "mean EPE, px (dense)",
    "sparse_1px": "sparse 1px: at the method's own points",
    "stereo_outliers": "stereo outliers (> 1 px)",
    "density": "density: points per valid pixel",
    "radial_gain": "radial gain (1 = unbiased)",
    "range_error": "range: median |r - r_true| / r_true",
    "ttc_error": "time to contact: median relative error",
}

#: Units of the keys a rig builder sweeps, for the x-axis label (docs/scene_format.md).
UNITS = {
    "optics.f_number": "inf = pinhole",
    "optics.focus_distance": "m from the lens",
    "camera.exposure": "fraction of full well per unit radiance",
    "camera.shutter": "fraction of the frame interval",
}
#: Units by the key's last part (the rig errors of [rig.errors.camN]).
UNITS_BY_NAME = {"mirror_tilt": "deg", "camera_tilt": "deg", "cone_angle": "deg, 90 ideal",
                 "mirror_offset": "m", "camera_offset": "m"}  # fmt: skip


def _unit(key: str) -> str:
    unit = UNITS.get(key) or UNITS_BY_NAME.get(key.rsplit(".", 1)[-1])
    return f" ({unit})" if unit else ""


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


#: Line style by what omniflow was told about the rig (``--registration``): a row and its
#: ``+registration=`` twins share a colour.
LINESTYLES = {"recorded": "-", "none": "--", "card": ":"}


def _styles(names: list[str]) -> dict[str, tuple[str, Any, str]]:
    """(label, colour, line style) per row: one colour per method, the style by its
    registration; an omniflow row's label says "recorded rig" when it has twins (on a
    rig-error sweep: registered by the true errors)."""
    import matplotlib

    bases = list(dict.fromkeys(n.partition("+registration=")[0] for n in names))
    cycle = [c["color"] for c in matplotlib.rcParams["axes.prop_cycle"]]
    twins = any("+registration=" in n for n in names)
    out = {}
    for n in names:
        base, _, reg = n.partition("+registration=")
        colour = cycle[bases.index(base) % len(cycle)]
        recorded = twins and not reg and n.startswith("omniflow")
        label = f"{n} (recorded rig: its true errors)" if recorded else n
        out[n] = (label, colour, LINESTYLES.get(reg or "recorded", "-."))
    return out


def sweep_plot(sweep: Mapping[str, Any], path: Path) -> None:
    """Draw the sweep's metrics (validation.sweep.METRICS) against its values.

    The values sit at even steps with their labels (a pinhole's inf and an error's
    vector have no place on a numeric axis); a point where a method gave no value is
    left out of its line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key, labels = sweep["parameter"], list(sweep["values"])
    names = list(dict.fromkeys(r["method"] for r in sweep["rows"]))
    styles = _styles(names)
    fig, axes = plt.subplots(2, 4, figsize=(18, 7.5), sharex=True, layout="constrained")
    for ax, (metric, label) in zip(axes.flat, METRICS.items(), strict=True):
        for name in names:
            by_value = {r["index"]: _num(r.get(metric)) for r in sweep["rows"]
                        if r["method"] == name}  # fmt: skip
            xs = [i for i in range(len(labels)) if not math.isnan(by_value.get(i, math.nan))]
            scale = 100.0 if metric not in ("epe", "radial_gain") else 1.0
            key_label, colour, style = styles[name]
            ax.plot(xs, [scale * by_value[i] for i in xs], marker="o", label=key_label,
                    color=colour, linestyle=style)  # fmt: skip
        unit = {"epe": " (px)", "radial_gain": ""}.get(metric, " (%)")
        ax.set_title(label, fontsize=10)
        ax.set_ylabel(f"{metric}{unit}")
        if metric == "radial_gain":
            ax.axhline(1.0, color="k", lw=0.8)
        if metric == "density":  # a sparse method's 0.3-7 % beside a dense one's 100 %
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xticks(range(len(labels)), labels, rotation=30 if len(labels) > 5 else 0)
        ax.set_xlabel(key + _unit(key))
    handles, keys = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, keys, loc="outside lower center", ncol=min(len(keys), 3), fontsize=9)
    fig.suptitle(f"Accuracy against {key}: {Path(sweep['scene']).name}, one render per value, "
                 f"{sweep['resolution']} px, {sweep['frames']} frames")  # fmt: skip
    save(fig, path)
    plt.close(fig)
