"""Write the report: per-frame CSV, summary JSON, figures, Markdown and HTML.

Layout of ``REPORT_DIR``::

    report.md, report.html     the same content; images by relative path
    summary.json               pooled statistics per method (summary.FORMAT)
    frames.csv                 one row per frame pair, method, point set, camera
    figures/*.png              inputs, panorama, flow, error maps, plots

Every file is written atomically (temporary name, then rename).
"""

from __future__ import annotations

import csv
import html
import io
import itertools
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.imageio import atomic_output, atomic_write_text
from omniflow.jsonio import jsonable

from .metrics import RANGE_BINS, SPEED_BINS, bin_label
from .runner import Results
from .summary import flat_table, pooled_flow, summarize

__all__ = ["write_report"]


# -- small document model rendered to both Markdown and HTML ---------------------------


class _Doc:
    def __init__(self) -> None:
        self.blocks: list[tuple[str, Any]] = []

    def h(self, level: int, text: str) -> None:
        self.blocks.append(("h", (level, text)))

    def p(self, text: str) -> None:
        self.blocks.append(("p", text))

    def code(self, text: str) -> None:
        self.blocks.append(("code", text))

    def table(self, header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
        self.blocks.append(("table", (list(header), [list(r) for r in rows])))

    def img(self, path: str, alt: str) -> None:
        self.blocks.append(("img", (path, alt)))

    def markdown(self) -> str:
        out = []
        for kind, val in self.blocks:
            if kind == "h":
                out.append("#" * val[0] + " " + val[1])
            elif kind == "p":
                out.append(val)
            elif kind == "code":
                out.append("```\n" + val + "\n```")
            elif kind == "img":
                out.append(f"![{val[1]}]({val[0]})")
            elif kind == "table":
                header, rows = val
                lines = [
                    "| " + " | ".join(header) + " |",
                    "|" + "|".join("---" for _ in header) + "|",
                ]
                lines += ["| " + " | ".join(r) + " |" for r in rows]
                out.append("\n".join(lines))
        return "\n\n".join(out) + "\n"

    def html(self, title: str) -> str:
        body = []
        for kind, val in self.blocks:
            if kind == "h":
                body.append(f"<h{val[0]}>{html.escape(val[1])}</h{val[0]}>")
            elif kind == "p":
                body.append(f"<p>{_inline_html(val)}</p>")
            elif kind == "code":
                body.append(f"<pre><code>{html.escape(val)}</code></pre>")
            elif kind == "img":
                src, alt = (html.escape(v, quote=True) for v in val)
                body.append(
                    f'<figure><img src="{src}" alt="{alt}" loading="eager">'
                    f"<figcaption>{html.escape(val[1])}</figcaption></figure>"
                )
            elif kind == "table":
                header, rows = val
                th = "".join(f"<th>{html.escape(c)}</th>" for c in header)
                trs = "".join(
                    "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>"
                    for r in rows
                )
                body.append(
                    f'<div class="scroll"><table><thead><tr>{th}</tr></thead>'
                    f"<tbody>{trs}</tbody></table></div>"
                )
        return _HTML_TEMPLATE.format(title=html.escape(title), body="\n".join(body))


def _inline_html(text: str) -> str:
    # Markdown's `code` spans and **bold** only; everything else escaped.
    parts = html.escape(text).split("`")
    out = []
    for i, part in enumerate(parts):
        if i % 2:
            out.append(f"<code>{part}</code>")
        else:
            bold = part.split("**")
            out.append("".join(f"<b>{b}</b>" if j % 2 else b for j, b in enumerate(bold)))
    return "".join(out)


_HTML_TEMPLATE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>
body {{ font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 24px auto;
       max-width: 1240px; padding: 0 16px; color: #1b1b1b; background: #fff; line-height: 1.45; }}
h1 {{ font-size: 1.7em; border-bottom: 2px solid #345; padding-bottom: 4px; }}
h2 {{ font-size: 1.3em; margin-top: 1.6em; color: #234; }}
h3 {{ font-size: 1.1em; color: #234; }}
table {{ border-collapse: collapse; font-size: 0.82em; margin: 8px 0 16px; }}
th, td {{ border: 1px solid #c8ccd2; padding: 3px 7px; text-align: right; white-space: nowrap; }}
th {{ background: #e8edf3; position: sticky; top: 0; }}
td:first-child, th:first-child {{ text-align: left; }}
tr:nth-child(even) td {{ background: #f6f8fa; }}
.scroll {{ overflow-x: auto; }}
figure {{ margin: 12px 0 20px; }}
figure img {{ max-width: 100%; height: auto; border: 1px solid #dde; }}
figcaption {{ font-size: 0.85em; color: #555; }}
code, pre {{ background: #f3f4f6; border-radius: 3px; }}
pre {{ padding: 8px; overflow-x: auto; }}
</style>
</head>
<body>
{body}
</body>
</html>
"""


# -- formatting -----------------------------------------------------------------------


def _f(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, int | np.integer) and not isinstance(v, bool):
        return str(int(v))
    v = float(v)
    if not math.isfinite(v):
        return "–"
    if v != 0 and (abs(v) < 10**-(digits) or abs(v) >= 1e5):
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}f}" if abs(v) < 10 else f"{v:.{max(0, digits - 2)}f}"


def _pct(v: Any) -> str:
    if v is None or not math.isfinite(float(v)):
        return "–"
    return f"{100 * float(v):.1f} %"


# -- figures ------------------------------------------------------------------------------


def _save(fig: Any, path: Path) -> None:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")


def _figures(results: Results, summary: Mapping[str, Any], fig_dir: Path) -> dict[str, str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omniflow.draw import color_wheel, flow_to_color

    out: dict[str, str] = {}
    snap = results.snapshot
    fig_dir.mkdir(parents=True, exist_ok=True)
    if snap is not None:
        # Inputs.
        fig, axes = plt.subplots(1, 2, figsize=(9, 4.6))
        for ax, cam in zip(axes, ("cam1", "cam2"), strict=True):
            ax.imshow(snap.images[cam], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
            ax.set_title(f"{cam}, frame {snap.t} (8-bit input)")
            ax.axis("off")
        fig.tight_layout()
        _save(fig, fig_dir / "inputs.png")
        plt.close(fig)
        out["inputs"] = "figures/inputs.png"

        if snap.panorama is not None:
            pan = snap.panorama
            fig, ax = plt.subplots(figsize=(12, max(2.0, 12 * pan.shape[0] / pan.shape[1] + 0.8)))
            ax.imshow(pan, cmap="gray", vmin=0, vmax=255, aspect="auto", interpolation="nearest")
            ax.set_title("cam1 unwarped (eq. 6-7): theta 0..2 pi left to right, rim at the top")
            ax.set_xlabel("column (theta)")
            ax.set_ylabel("row (h_i decreasing)")
            fig.tight_layout()
            _save(fig, fig_dir / "panorama.png")
            plt.close(fig)
            out["panorama"] = "figures/panorama.png"

        for cam in ("cam1", "cam2"):
            tr = snap.truth[cam]
            valid = tr["gt.valid"] > 0.5
            gdx, gdy = tr["gt.flow.dx"], tr["gt.flow.dy"]
            mag = np.hypot(gdx, gdy)[valid]
            vmax = (
                float(np.percentile(mag[np.isfinite(mag)], 99)) if np.isfinite(mag).any() else 1.0
            )
            vmax = vmax if vmax > 0 else 1.0
            panels = [("ground truth (dense)", flow_to_color(gdx, gdy, max_flow=vmax, mask=valid))]
            for b, fields in snap.dense.items():
                f = fields[cam]
                panels.append(
                    (f"{b} (dense)", flow_to_color(f[..., 0], f[..., 1], max_flow=vmax, mask=valid))
                )
            pts = snap.points.get(cam)
            if pts is not None:
                shape = valid.shape
                panels.append(
                    (
                        "omniflow default (at its points)",
                        _scatter_color(pts["x"], pts["y"], pts["dx"], pts["dy"], shape, vmax),
                    )
                )
                panels.append(
                    (
                        "ground truth at the same points",
                        _scatter_color(pts["x"], pts["y"], pts["gt_dx"], pts["gt_dy"], shape, vmax),
                    )
                )
            ncol = 3
            nrow = math.ceil(len(panels) / ncol)
            fig, axes = plt.subplots(
                nrow, ncol, figsize=(4 * ncol, 4.3 * nrow + 0.4), layout="constrained"
            )
            for ax in np.ravel(axes):
                ax.axis("off")
            for ax, (title, img) in zip(np.ravel(axes), panels, strict=False):
                ax.imshow(img, interpolation="nearest")
                ax.set_title(title, fontsize=10)
            key = np.ravel(axes)[-1] if len(panels) < nrow * ncol else None
            if key is not None:
                key.imshow(color_wheel(128))
                key.set_title(f"colour key: saturated at {vmax:.2f} px", fontsize=10)
            fig.suptitle(f"{cam} flow, frame {snap.t} -> {snap.t + 1} (Middlebury colour coding)")
            _save(fig, fig_dir / f"flow_{cam}.png")
            plt.close(fig)
            out[f"flow_{cam}"] = f"figures/flow_{cam}.png"

        # Error maps (cam1): dense baselines and omniflow's points, one colour scale.
        tr = snap.truth["cam1"]
        valid = tr["gt.valid"] > 0.5
        maps = []
        for b, fields in snap.dense.items():
            f = fields["cam1"]
            epe = np.hypot(f[..., 0] - tr["gt.flow.dx"], f[..., 1] - tr["gt.flow.dy"])
            maps.append((f"{b}: EPE (px)", np.where(valid, epe, np.nan), None))
        pts = snap.points.get("cam1")
        if pts is not None:
            epe = np.hypot(pts["dx"] - pts["gt_dx"], pts["dy"] - pts["gt_dy"])
            maps.append(
                ("omniflow default: EPE at its points (px)", None, (pts["x"], pts["y"], epe))
            )
        if maps:
            vals = np.concatenate(
                [
                    np.ravel(m[1][np.isfinite(m[1])])
                    if m[1] is not None
                    else m[2][2][np.isfinite(m[2][2])]
                    for m in maps
                ]
            )
            vmax = float(np.percentile(vals, 95)) if vals.size else 1.0
            vmax = vmax if vmax > 0 else 1.0
            cmap = matplotlib.colormaps["magma"].with_extremes(bad="#b8bcc4")
            fig, axes = plt.subplots(
                1, len(maps), figsize=(3.6 * len(maps) + 1.2, 4.0), squeeze=False,
                layout="constrained",
            )  # fmt: skip
            im = None
            for ax, (title, dense, sparse) in zip(axes[0], maps, strict=True):
                if dense is not None:
                    im = ax.imshow(dense, cmap=cmap, vmin=0, vmax=vmax, interpolation="nearest")
                else:
                    ax.imshow(np.full(valid.shape, np.nan), cmap=cmap, vmin=0, vmax=vmax)
                    im = ax.scatter(sparse[0] - 0.5, sparse[1] - 0.5, c=sparse[2], s=5,
                                    cmap=cmap, vmin=0, vmax=vmax)  # fmt: skip
                ax.set_title(title, fontsize=9)
                ax.axis("off")
            if im is not None:
                fig.colorbar(im, ax=list(axes[0]), shrink=0.8, label="endpoint error, px")
            fig.suptitle(
                f"cam1 error maps, frame {snap.t} (colour clipped at the 95th percentile; "
                "grey: no scene)"
            )
            _save(fig, fig_dir / "error_maps.png")
            plt.close(fig)
            out["error_maps"] = "figures/error_maps.png"

    # Error vs range and vs speed: binned medians from the pooled per-point errors.
    methods = _plot_methods(results)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.4))
    for name, pts in methods:
        err = pooled_flow(results, name, pts, "cam1")
        if err is None or not err["epe"].size:
            continue
        _binned(axes[0], err["range"], err["epe"], _edges(err["range"]), name)
    axes[0].set_xlabel("true range r (m)")
    axes[0].set_ylabel("median EPE (px), cam1")
    axes[0].set_title("flow error vs range")
    ax = axes[1]
    # One line per matching rule: stereo does not depend on the flow choices.
    by_rule: dict[str, str] = {}
    for m in results.methods:
        if m.kind == "omniflow":
            by_rule.setdefault(str(m.config.get("match_method", m.name)), m.name)
    for name in by_rule.values():
        frames = results.stereo.get(name, [])
        if not frames:
            continue
        rng = np.concatenate([f["range"] for f in frames])
        rel = np.concatenate([f["rel_r"] for f in frames])
        if rng.size:
            _binned(ax, rng, rel, _edges(rng), name)
    ax.set_xlabel("true range r (m)")
    ax.set_ylabel("median |r - r_gt| / r_gt")
    ax.set_title("stereo range error vs range")
    for a in axes:
        a.grid(alpha=0.3)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, fig_dir / "error_vs_range.png")
    plt.close(fig)
    out["error_vs_range"] = "figures/error_vs_range.png"

    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    for name, pts in methods:
        err = pooled_flow(results, name, pts, "cam1")
        if err is None or not err["epe"].size:
            continue
        sel = err["noc"]
        _binned(ax, err["speed"][sel], err["epe"][sel], _edges(err["speed"][sel]), name)
    ax.set_xlabel("true speed (px/frame)")
    ax.set_ylabel("median EPE (px), cam1, non-occluded")
    ax.set_title("flow error vs speed")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, fig_dir / "error_vs_speed.png")
    plt.close(fig)
    out["error_vs_speed"] = "figures/error_vs_speed.png"

    # Accuracy vs time, every row.
    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    for row in flat_table(summary):
        if row["points"] == "dense":
            continue
        y = row.get("cam1_epe_median")
        if y is None or not math.isfinite(y) or not math.isfinite(row["time_ms"]):
            continue
        marker = "o" if row["method"].startswith("omniflow") else "s"
        ax.scatter(row["time_ms"], y, marker=marker)
        ax.annotate(row["method"].replace("omniflow", "of"), (row["time_ms"], y), fontsize=6)
    ax.set_xscale("log")
    ax.set_xlabel("time per frame pair, both cameras (ms)")
    ax.set_ylabel("median EPE cam1 (px) at omniflow's points")
    ax.set_title("accuracy vs time")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    _save(fig, fig_dir / "accuracy_vs_time.png")
    plt.close(fig)
    out["accuracy_vs_time"] = "figures/accuracy_vs_time.png"
    return out


def _plot_methods(results: Results) -> list[tuple[str, str]]:
    """The default omniflow variant, the paper's rule, and the baselines at its points."""
    omni = [m.name for m in results.methods if m.kind == "omniflow"]
    chosen = omni[:1] + [n for n in omni[1:] if "paper" in n][:1]
    chosen += [n for n in omni[1:] if "pooled" in n and "paper" not in n][:1]
    out = [(n, "own") for n in chosen]
    out += [(m.name, "omniflow points") for m in results.methods if m.kind == "baseline"]
    return out


def _edges(values: NDArray, n: int = 8) -> NDArray:
    """Quantile bin edges with about 10 or more points a bin (at most ``n`` bins)."""
    v = values[np.isfinite(values)]
    n = min(n, v.size // 10)
    if n < 1:
        return np.array([v.min(), v.max()]) if v.size else np.array([0.0, 1.0])
    return np.unique(np.percentile(v, np.linspace(0, 100, n + 1)))


def _binned(ax: Any, x: NDArray, y: NDArray, edges: NDArray, label: str) -> None:
    xs, ys = [], []
    for lo, hi in itertools.pairwise(edges):
        sel = (x >= lo) & (x <= hi) & np.isfinite(y)
        if sel.sum() >= 3:
            xs.append(float(np.median(x[sel])))
            ys.append(float(np.median(y[sel])))
    if xs:
        ax.plot(xs, ys, marker="o", ms=3, label=label)


def _scatter_color(
    x: NDArray, y: NDArray, dx: NDArray, dy: NDArray, shape: tuple[int, int], vmax: float
) -> NDArray:
    from omniflow.draw import flow_to_color

    img = np.zeros((*shape, 3), dtype=np.uint8)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(dx) & np.isfinite(dy)
    cols = np.floor(x[ok]).astype(int)
    rows = np.floor(y[ok]).astype(int)
    colours = flow_to_color(dx[ok], dy[ok], max_flow=vmax)
    # Each point as a small square (about 1 % of the image), so sparse points stay visible.
    rad = max(1, round(max(shape) / 100))
    for di in range(-rad, rad + 1):
        for dj in range(-rad, rad + 1):
            r, c = rows + di, cols + dj
            inside = (c >= 0) & (c < shape[1]) & (r >= 0) & (r < shape[0])
            img[r[inside], c[inside]] = colours[inside]
    return img


# -- tables and text -------------------------------------------------------------------


def _method_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = ["method", "points", "n cam1", "EPE med", "EPE mean", "EPE p90", "noc EPE",
              "occ EPE", ">1px", ">3px", "EPE cam2", "DIS same pts", "stereo >1px",
              "r rel err", "match rate", "ms / frame"]  # fmt: skip
    rows = []
    for m, r in zip(summary["methods"], flat_table(summary), strict=True):
        f = m["flow"].get("cam1", {})
        rows.append([
            r["method"], r["points"], _f(r.get("cam1_n")), _f(r.get("cam1_epe_median")),
            _f(r.get("cam1_epe_mean")), _f(f.get("all", {}).get("epe", {}).get("p90")),
            _f(r.get("cam1_noc_epe_median")), _f(r.get("cam1_occ_epe_median")),
            _pct(r.get("cam1_out1")), _pct(r.get("cam1_out3")), _f(r.get("cam2_epe_median")),
            _f(r.get("dis_same_points_cam1_epe_median")), _pct(r.get("stereo_outliers")),
            _f(r.get("rel_r_median")), _pct(r.get("match_rate")), _f(r.get("time_ms"), 1),
        ])  # fmt: skip
    return header, rows


def _polar_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = ["method", "points"]
    for cam in ("cam1", "cam2"):
        header += [f"{cam} |dh| med", f"{cam} |h dθ| med", f"{cam} AE med (°)"]
    rows = []
    for r in flat_table(summary):
        cells = [r["method"], r["points"]]
        for cam in ("cam1", "cam2"):
            cells += [
                _f(r.get(f"{cam}_dh_median")),
                _f(r.get(f"{cam}_hdtheta_median")),
                _f(r.get(f"{cam}_ae_median"), 2),
            ]
        rows.append(cells)
    return header, rows


def _headline_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The default omniflow variant, the paper's configuration, the default flow step on
    true matches, and the baselines at the default variant's points: median EPE of both
    cameras, stereo range error, time."""
    header = [
        "method",
        "EPE cam1 (px)",
        "EPE cam2 (px)",
        ">1px cam1",
        "r rel err",
        "stereo >1px",
        "ms / frame",
    ]
    rows = []
    omni = [m for m in summary["methods"] if m["kind"] == "omniflow"]
    picked = omni[:1] + [m for m in omni[1:] if _is_paper(m)][:1]
    picked += [m for m in omni if m.get("config", {}).get("match_method") == "truth"][:1]
    picked += [
        m
        for m in summary["methods"]
        if m["kind"] == "baseline" and m["points"] == "omniflow points"
    ]
    for m in picked:
        f1, f2 = m["flow"].get("cam1", {}), m["flow"].get("cam2", {})
        st = m.get("stereo") or {}
        label = m["name"] + (" (default)" if m.get("default") else "")
        label += " (paper)" if m["kind"] == "omniflow" and _is_paper(m) else ""
        label += " at the default's points" if m["kind"] == "baseline" else ""
        a1, a2, sa = f1.get("all", {}), f2.get("all", {}), st.get("all", {})
        rows.append(
            [
                label,
                _f(a1.get("epe", {}).get("median")),
                _f(a2.get("epe", {}).get("median")),
                _pct(a1.get("out1")),
                _f(sa.get("rel_r", {}).get("median")),
                _pct(sa.get("outliers")),
                _f(1000 * _nan(m["time_per_frame"]["median_s"]), 1),
            ]
        )
    return header, rows


def _is_paper(m: Mapping[str, Any]) -> bool:
    return bool(m.get("paper"))


def _speed_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    labels = [bin_label(lo, hi, "px") for lo, hi in itertools.pairwise(SPEED_BINS)]
    header = ["method", "points"] + [f"EPE {lab} (n)" for lab in labels]
    rows = []
    for m in summary["methods"]:
        f = m["flow"].get("cam1")
        if f is None:
            continue
        cells = []
        for lab in labels:
            b = f["speed"].get(lab, {})
            cells.append(f"{_f(b.get('epe', {}).get('median'))} ({b.get('n', 0)})")
        rows.append([m["name"], m["points"], *cells])
    return header, rows


def _range_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    labels = [bin_label(lo, hi, "m") for lo, hi in itertools.pairwise(RANGE_BINS)]
    header = ["method"] + [f"r rel err {lab} (n, >1px)" for lab in labels] + ["|h| err med (m)"]
    rows = []
    for m in summary["methods"]:
        st = m.get("stereo")
        if not st:
            continue
        cells = []
        for lab in labels:
            b = st["range"][lab]
            cells.append(f"{_f(b['rel_r']['median'])} ({b['n']}, {_pct(b['outliers'])})")
        rows.append([m["name"], *cells, _f(st["all"]["err_h"]["median"])])
    return header, rows


def _derived_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = [
        "method",
        "|dr/dt err| med (mm/frame)",
        "true |dr/dt| med (mm/frame)",
        "TTC rel err med (n)",
        "odometry |w err| (mrad/frame)",
        "|V err| (mm/frame)",
        "tangential only: |w err|",
        "|V err|",
    ]
    rows = []
    for m in summary["methods"]:
        d = m.get("derived")
        if not d:
            continue
        ob, ot = d.get("odometry_both", {}), d.get("odometry_tangential", {})

        def milli(block: Mapping[str, Any], key: str) -> str:
            v = block.get(key, {}).get("median")
            return _f(None if v is None else 1000 * v)

        rows.append(
            [
                m["name"],
                _f(1000 * _nan(d["dr_dt_abs_error_m_per_frame"]["median"])),
                _f(1000 * _nan(d["dr_dt_true_abs_m_per_frame"]["median"])),
                f"{_f(d['ttc_relative_error']['median'])} ({d['ttc_relative_error']['n']})",
                milli(ob, "yaw_rate_abs_error_rad_per_frame"),
                milli(ob, "velocity_abs_error_m_per_frame"),
                milli(ot, "yaw_rate_abs_error_rad_per_frame"),
                milli(ot, "velocity_abs_error_m_per_frame"),
            ]
        )
    return header, rows


def _nan(v: Any) -> float:
    return math.nan if v is None else float(v)


def _document(summary: Mapping[str, Any], figures: Mapping[str, str], command: str | None) -> _Doc:
    ds = summary["dataset"]
    doc = _Doc()
    doc.h(1, f"omnivalidate: {ds['scene']}")
    doc.p(
        f"Dataset `{ds['path']}`: {ds['size'][0]}x{ds['size'][1]} px, {ds['frames']} frames, "
        f"frame interval {ds['frame_interval_s']} s, rig d = {ds['rig']['d']} m, "
        f"R = {ds['rig']['R']} m, s = {ds['rig']['s']} m. Scored frame pairs t -> t + 1 for "
        f"t = {', '.join(str(t) for t in ds['pairs'])}."
    )
    if command:
        doc.p("Reproduce with:")
        doc.code(command)
    doc.p(
        "**Units.** Flow in pixels per frame interval. omniflow estimates velocities per frame "
        "interval (eq. 16 with t in frames); the ground truth is the displacement of each "
        "material point from frame t to t + 1, and the two are compared directly. Every method "
        "sees the same 8-bit frames. Times are wall-clock seconds per frame pair for both "
        "cameras, measured in this run. Baselines are dense; they are scored at the points of "
        "the default omniflow variant (`omniflow points`), at every valid pixel (`dense`), and "
        "for each variant at that variant's own points (column `DIS same pts`)."
    )
    doc.h(2, "Headline")
    doc.table(*_headline_table(summary))
    doc.h(2, "Inputs")
    for key, alt in (("inputs", "input frames"), ("panorama", "unwarped panorama of cam1")):
        if key in figures:
            doc.img(figures[key], alt)
    doc.h(2, "Flow: estimated vs ground truth")
    for key, alt in (
        ("flow_cam1", "estimated vs ground-truth flow, cam1"),
        ("flow_cam2", "estimated vs ground-truth flow, cam2"),
        ("error_maps", "error maps, cam1"),
    ):
        if key in figures:
            doc.img(figures[key], alt)
    doc.h(2, "Methods side by side (accuracy and time)")
    doc.p(
        "EPE = endpoint error (px), noc / occ = non-occluded / occluded points "
        "(`gt.flow.valid`), AE = angular error, >1px / >3px = outlier rates, stereo >1px = "
        "matches whose h_2 is more than 1 px from `gt.stereo.h_other`; r rel err = median "
        "|r - r_gt| / r_gt; match rate = matches / significant points the other camera sees."
    )
    doc.table(*_method_table(summary))
    doc.h(3, "Polar components and angular error")
    doc.table(*_polar_table(summary))
    doc.h(2, "Flow error by speed (cam1, non-occluded)")
    doc.table(*_speed_table(summary))
    if "error_vs_speed" in figures:
        doc.img(figures["error_vs_speed"], "error vs speed")
    doc.h(2, "Stereo by range")
    doc.table(*_range_table(summary))
    if "error_vs_range" in figures:
        doc.img(figures["error_vs_range"], "error vs range")
    doc.h(2, "Derived quantities")
    doc.p(
        "dr/dt and time to contact (TTC, frames) against the objects' known motion from the "
        "poses in dataset.json (TTC over points whose true range shrinks by more than 0.1 % per "
        "frame); odometry (omniflow.applications.odometry, robust fit) against the robot's "
        "known motion."
    )
    doc.table(*_derived_table(summary))
    if "accuracy_vs_time" in figures:
        doc.img(figures["accuracy_vs_time"], "accuracy vs time")
    for note in summary.get("notes", []):
        doc.p(note)
    return doc


def _csv_text(rows: Sequence[Mapping[str, Any]]) -> str:
    keys: list[str] = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _csv_cell(r.get(k)) for k in keys})
    return buf.getvalue()


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float | np.floating):
        return "" if not math.isfinite(float(v)) else repr(float(v))
    return v


def write_report(results: Results, out_dir: str | Path, *, command: str | None = None) -> dict:
    """Write CSV, JSON, figures, Markdown and HTML into ``out_dir``; return the summary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = jsonable(summarize(results))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1, allow_nan=False) + "\n")
    atomic_write_text(out / "frames.csv", _csv_text(results.rows))
    figures = _figures(results, summary, out / "figures")
    doc = _document(summary, figures, command)
    atomic_write_text(out / "report.md", doc.markdown())
    atomic_write_text(out / "report.html", doc.html(f"omnivalidate: {summary['dataset']['scene']}"))
    return summary
