"""The report's figures (matplotlib, Agg), each written atomically at :data:`DPI`."""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.io.imageio import atomic_output

from .report_doc import num
from .results import FramePair, Results
from .summary import flat_table, pooled_flow

__all__ = ["DPI", "draw_figures", "sweep_figure"]


#: Resolution of every figure (dots per inch).
DPI = 150


def save(fig: Any, path: Path) -> None:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png")


def draw_figures(results: Results, summary: Mapping[str, Any], fig_dir: Path) -> dict[str, str]:
    """Draw every figure of the report into ``fig_dir``; returns name -> relative path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out: dict[str, str] = {}
    snap = results.snapshot
    fig_dir.mkdir(parents=True, exist_ok=True)
    if snap is not None:
        out.update(_input_figures(plt, snap, fig_dir))
        out.update(_flow_figures(plt, snap, fig_dir))
        out.update(_error_map_figure(plt, snap, fig_dir))
    out.update(_range_speed_figures(plt, results, fig_dir))
    out.update(reliability_figure(plt, summary, fig_dir))
    # Accuracy vs time, every row at the default's points (zero flow left out: no time).
    _accuracy_vs_time(plt, summary, fig_dir / "accuracy_vs_time.png")
    out["accuracy_vs_time"] = "figures/accuracy_vs_time.png"
    return out


def _input_figures(plt: Any, snap: FramePair, fig_dir: Path) -> dict[str, str]:
    """The two input images and cam1's panorama."""
    out: dict[str, str] = {}
    # Inputs.
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.8), layout="constrained")
    for ax, cam in zip(axes, ("cam1", "cam2"), strict=True):
        ax.imshow(snap.images[cam], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_title(f"{cam}, frame {snap.t} (input to every method)")
        ax.axis("off")
    save(fig, fig_dir / "inputs.png")
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
        save(fig, fig_dir / "panorama.png")
        plt.close(fig)
        out["panorama"] = "figures/panorama.png"

    return out


def _flow_figures(plt: Any, snap: FramePair, fig_dir: Path) -> dict[str, str]:
    """Per camera: the true flow, each dense baseline and omniflow's points, colour-coded."""
    from omniflow.io.draw import color_wheel, flow_to_color

    out: dict[str, str] = {}
    for cam in ("cam1", "cam2"):
        tr = snap.truth[cam]
        valid = tr["gt.valid"] > 0.5
        gdx, gdy = tr["gt.flow.dx"], tr["gt.flow.dy"]
        mag = np.hypot(gdx, gdy)[valid]
        vmax = float(np.percentile(mag[np.isfinite(mag)], 99)) if np.isfinite(mag).any() else 1.0
        vmax = vmax if vmax > 0 else 1.0
        panels = [("ground truth (dense)", flow_to_color(gdx, gdy, max_flow=vmax, mask=valid))]
        for b, fields in snap.dense.items():
            if b == "zero-flow":  # uniformly white: nothing to see
                continue
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
        nrow = math.ceil((len(panels) + 1) / ncol)  # + 1: the colour key, always shown
        fig, axes = plt.subplots(
            nrow, ncol, figsize=(4 * ncol, 4.3 * nrow + 0.4), layout="constrained"
        )
        for ax in np.ravel(axes):
            ax.axis("off")
        for ax, (title, img) in zip(np.ravel(axes), panels, strict=False):
            ax.imshow(img, interpolation="nearest")
            ax.set_title(title, fontsize=10)
        key = np.ravel(axes)[-1]
        key.imshow(color_wheel(128))
        key.set_title(f"colour key: full saturation at {vmax:.2f} px", fontsize=10)
        fig.suptitle(f"{cam} flow, frame {snap.t} -> {snap.t + 1} (Middlebury colour coding)")
        save(fig, fig_dir / f"flow_{cam}.png")
        plt.close(fig)
        out[f"flow_{cam}"] = f"figures/flow_{cam}.png"

    return out


def _error_map_figure(plt: Any, snap: FramePair, fig_dir: Path) -> dict[str, str]:
    """cam1 error maps: dense baselines and omniflow's points, one colour scale."""
    import matplotlib

    out: dict[str, str] = {}
    # Error maps (cam1): dense baselines and omniflow's points, one colour scale.
    tr = snap.truth["cam1"]
    valid = tr["gt.valid"] > 0.5
    maps = []
    for b, fields in snap.dense.items():
        if b == "zero-flow":  # its error map is the truth's magnitude
            continue
        f = fields["cam1"]
        epe = np.hypot(f[..., 0] - tr["gt.flow.dx"], f[..., 1] - tr["gt.flow.dy"])
        maps.append((f"{b}: EPE (px)", np.where(valid, epe, np.nan), None))
    pts = snap.points.get("cam1")
    if pts is not None:
        epe = np.hypot(pts["dx"] - pts["gt_dx"], pts["dy"] - pts["gt_dy"])
        maps.append(("omniflow default: EPE at its points (px)", None, (pts["x"], pts["y"], epe)))
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
                if not np.size(sparse[2]):  # a grey panel alone reads as a broken figure
                    _no_data(ax, "no points on this frame")
            ax.set_title(title, fontsize=9)
            ax.axis("off")
        if im is not None:
            fig.colorbar(im, ax=list(axes[0]), shrink=0.8, label="endpoint error, px")
        fig.suptitle(
            f"cam1 error maps, frame {snap.t} (colour clipped at the 95th percentile; "
            "grey: no scene)"
        )
        save(fig, fig_dir / "error_maps.png")
        plt.close(fig)
        out["error_maps"] = "figures/error_maps.png"

    return out


def reliability_figure(plt: Any, summary: Mapping[str, Any], fig_dir: Path) -> dict[str, str]:
    """The reliability diagram of each method that predicts sigmas: per quantity (cam1,
    cam2 flow, range), the observed 68.3 % and 95.4 % error quantiles of each bin of
    predicted sigma against the bin's median sigma; calibrated points lie on the lines
    y = sigma and y = 2 sigma. Nothing when no method predicts sigmas."""
    methods = [m for m in summary["methods"] if m.get("calibration")]
    if not methods:
        return {}
    quantities = list(methods[0]["calibration"])
    fig, axes = plt.subplots(1, len(quantities), figsize=(5.2 * len(quantities), 5.2))
    titles = {"cam1": "cam1 flow: endpoint error", "cam2": "cam2 flow: endpoint error",
              "range": "range: |r - r_gt|"}  # fmt: skip
    for ax, q in zip(np.atleast_1d(axes), quantities, strict=True):
        lo, hi = math.inf, 0.0
        unit = methods[0]["calibration"][q]["unit"]
        shares = []
        for i, m in enumerate(methods):
            b = m["calibration"][q]
            rel = b.get("reliability") or []
            if not rel:
                continue
            s = np.array([num(r["sigma"]) for r in rel])
            colour = f"C{i % 10}"
            q68 = [num(r["q68"]) for r in rel]
            q95 = [num(r["q95"]) for r in rel]
            ax.plot(s, q68, "o-", color=colour, label=f"{m['name']}: 68.3 % error quantile")
            ax.plot(s, q95, "s--", color=colour, label=f"{m['name']}: 95.4 % error quantile")
            shares.append(f"{m['name']}: {num(b['within1']):.0%} / {num(b['within2']):.0%}")
            pos = s[np.isfinite(s) & (s > 0)]
            if pos.size:
                lo, hi = min(lo, float(pos.min())), max(hi, float(pos.max()))
        if hi > 0 and math.isfinite(lo):
            line = np.array([lo, hi])
            ax.plot(line, line, color="0.4", lw=1, label="calibrated: y = sigma (68.3 %)")
            ax.plot(line, 2 * line, color="0.4", lw=1, ls=":",
                    label="calibrated: y = 2 sigma (95.4 %)")  # fmt: skip
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.xaxis.set_minor_formatter(plt.NullFormatter())  # labelled decades only
        else:
            _no_data(ax, "no point with truth")
        ax.set_xlabel(f"predicted sigma ({unit}), bin median")
        ax.set_ylabel(f"observed error quantile ({unit})")
        head = titles.get(q, q)
        # one line per method: within 1 / 2 sigma
        ax.set_title("\n".join([head, *(f"{t} within 1 / 2 sigma" for t in shares)]), fontsize=7)
    handles, labels = np.atleast_1d(axes)[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7)
    fig.suptitle("Reliability of the predicted sigmas (equal-count bins of predicted sigma)")
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    save(fig, fig_dir / "reliability.png")
    plt.close(fig)
    return {"reliability": "figures/reliability.png"}


def _range_speed_figures(plt: Any, results: Results, fig_dir: Path) -> dict[str, str]:
    """Error vs range and vs speed: binned medians from the pooled per-point errors."""
    out: dict[str, str] = {}
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
        else:
            _no_data(a, "no points to bin: the rows scored none")
    fig.tight_layout()
    save(fig, fig_dir / "error_vs_range.png")
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
    else:
        _no_data(ax, "no points to bin: the rows scored none")
    fig.tight_layout()
    save(fig, fig_dir / "error_vs_speed.png")
    plt.close(fig)
    out["error_vs_speed"] = "figures/error_vs_speed.png"

    return out


#: Units of the camera parameters (omnisim.camera), for the sweep's axis label.
_UNITS = {"read_noise": "electrons rms", "full_well": "electrons", "bits": "bits",
          "defocus": "px, Gaussian sigma", "vignetting": "fraction lost at the rim",
          "exposure": "fraction of full well per unit radiance", "gain": "unitless"}  # fmt: skip


def sweep_figure(sweep: Sequence[Mapping[str, Any]], fig_dir: Path) -> dict[str, str]:
    """Accuracy against the swept camera parameter: mean EPE and radial gain per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = sweep[0]["parameter"]
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), sharex=True, layout="constrained")
    names = list(dict.fromkeys(r["method"] for r in sweep))
    for col, cam in enumerate(("cam1", "cam2")):
        for name in names:
            rows = [r for r in sweep if r["method"] == name and r["camera"] == cam]
            if not rows:
                continue
            x = [float(r["value"]) for r in rows]
            axes[0, col].plot(x, [num(r["epe_mean"]) for r in rows], marker="o", label=name)
            axes[1, col].plot(x, [num(r["radial_gain"]) for r in rows], marker="o", label=name)
        axes[0, col].set_title(f"{cam}: mean EPE at each method's scored points")
        axes[0, col].set_ylabel("mean EPE (px)")
        axes[1, col].set_ylabel("radial gain (1 = unbiased)")
        axes[1, col].axhline(1.0, color="k", lw=0.8)
        axes[1, col].set_xlabel(f"camera {key}" + (f" ({_UNITS[key]})" if key in _UNITS else ""))
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
    axes[0, 1].legend(fontsize=7, loc="best")
    fig.suptitle(f"Accuracy vs camera {key} (one render, images re-formed per level)")
    save(fig, fig_dir / "camera_sweep.png")
    plt.close(fig)
    return {"camera_sweep": "figures/camera_sweep.png"}


def _wrap_at_commas(text: str, width: int) -> str:
    """``text`` in lines of at most ``width`` characters where it can be, broken after a
    comma or a plus (a row's name is one word of settings joined by "+", a preset row's
    by ","; kept whole, not split inside a setting), the later lines indented."""
    lines = [""]
    for piece in re.split(r"(?<=[,+])", text):
        if lines[-1].strip() and len(lines[-1]) + len(piece) > width:
            lines.append("    ")
            piece = piece.lstrip()
        lines[-1] += piece
    return "\n".join(lines)


def _no_data(ax: Any, text: str) -> None:
    """Say in the middle of the axes why they are empty."""
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=9)


def _accuracy_vs_time(plt: Any, summary: Mapping[str, Any], path: Path) -> None:
    """Median EPE (cam1) against time per frame pair, one numbered marker per row and a
    legend beside the axes (no labels to overlap). Rows far above the rest (the paper's
    configuration on hard scenes) are drawn at the top edge with their value in the legend."""
    import matplotlib.ticker

    rows = []
    for row in flat_table(summary):
        y, ms = row.get("cam1_epe_median"), row["time_ms"]
        if row["points"] == "dense" or row["method"] == "zero-flow":
            continue
        if y is None or not math.isfinite(y) or not math.isfinite(ms):
            continue
        rows.append((row["method"], ms, y))
    # the legend goes below the axes: long variant names beside them squeezed the plot
    fig, ax = plt.subplots(figsize=(9, 4.6 + 0.16 * len(rows)), layout="constrained")
    ax.set_title("accuracy vs time", fontsize=10)
    if rows:
        ys = np.array([r[2] for r in rows])
        top = float(np.median(ys)) * 4.0  # above this a row is drawn clipped at the top
        clip = ys > top
        ceiling = max(float(ys[~clip].max()) * 1.15, 1e-3) if (~clip).any() else float(ys.max())
        for i, (name, ms, y) in enumerate(rows, start=1):
            marker = "o" if name.startswith("omniflow") else "s"
            off = y > ceiling
            yp = ceiling if off else y
            label = f"{i}: {name} ({y:.3f} px, {ms:.0f} ms)" + (" - off scale" if off else "")
            # wrapped: a line wider than the figure (the paper's row, ~200 characters)
            # collapses the constrained layout
            label = _wrap_at_commas(label, 110)
            ax.scatter(ms, yp, marker="^" if off else marker, s=40, label=label, zorder=3)
            ax.annotate(str(i), (ms, yp), textcoords="offset points", xytext=(4, 3), fontsize=8)
        ax.set_ylim(0, ceiling * 1.05)
        note = (
            "^ = off scale: drawn at the top edge, its value in this list" if clip.any() else None
        )
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.16), frameon=False,
                  title=note, title_fontsize=7, alignment="left")  # fmt: skip
    else:  # empty axes alone read as a broken figure
        _no_data(ax, "no row has a median EPE to plot: no points were scored")
    ax.set_xscale("log")
    plain = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")
    ax.xaxis.set_major_formatter(plain)
    # minor labels at 2, 3 and 5 x 10^k only: every minor label crowded 70, 80, 90 together
    ax.xaxis.set_minor_locator(matplotlib.ticker.LogLocator(subs=(2.0, 3.0, 5.0)))
    ax.xaxis.set_minor_formatter(plain)
    ax.tick_params(axis="x", which="both", labelsize=8)
    ax.set_xlabel("time per frame pair, both cameras (ms, log scale)")
    ax.set_ylabel("median EPE, cam1 (px), at each row's points")
    ax.grid(alpha=0.3, which="both")
    save(fig, path)
    plt.close(fig)


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


#: Line styles and markers of the binned curves, in turn: rows with the same errors (the
#: default and a row whose extra knob changes nothing there) would otherwise draw one line
#: exactly over the other and hide it.
_LINESTYLES = ("-", "--", "-.", ":")
_MARKERS = ("o", "s", "^", "D", "v", "P", "X")


def _binned(ax: Any, x: NDArray, y: NDArray, edges: NDArray, label: str) -> None:
    """Medians of y in the bins of x, one line on ``ax``, styled apart from its others."""
    xs, ys = [], []
    for lo, hi in itertools.pairwise(edges):
        sel = (x >= lo) & (x <= hi) & np.isfinite(y)
        if sel.sum() >= 3:
            xs.append(float(np.median(x[sel])))
            ys.append(float(np.median(y[sel])))
    if xs:
        k = len(ax.get_lines())
        ax.plot(xs, ys, marker=_MARKERS[k % len(_MARKERS)], ms=4, mfc="none",
                ls=_LINESTYLES[k % len(_LINESTYLES)], label=label)  # fmt: skip


def _scatter_color(
    x: NDArray, y: NDArray, dx: NDArray, dy: NDArray, shape: tuple[int, int], vmax: float
) -> NDArray:
    from omniflow.io.draw import flow_to_color

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
