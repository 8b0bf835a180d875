"""The ``omniflow`` command's regions, odometry and position fix (``--region``,
``--auto-regions``, ``--odometry``, ``--landmark``): options, masks and their outputs."""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from omniflow.cli.common import CLIError, one_line, size_text
from omniflow.geometry.rig import Rig
from omniflow.io.imageio import ImageError, read_image

__all__ = [
    "check_region_options",
    "fit_odometry",
    "position_fix_block",
    "region_masks",
    "region_rows",
]


def check_region_options(args) -> None:
    """Region, landmark and odometry options: ranges, syntax, names (no file is read here)."""
    from omniflow.applications.regions import RegionError, parse_landmark, parse_region

    w = args.odometry_radial_weight
    if not (math.isfinite(w) and w >= 0):
        raise CLIError(f"--odometry-radial-weight {w}: expected a finite number >= 0")
    if args.auto_min_points < 1:
        raise CLIError(f"--auto-min-points {args.auto_min_points}: expected an integer >= 1")
    if args.auto_link is not None and not (math.isfinite(args.auto_link) and args.auto_link > 0):
        raise CLIError(f"--auto-link {args.auto_link}: expected a finite distance in px > 0")
    if not (math.isfinite(args.auto_residual) and args.auto_residual >= 1):
        raise CLIError(
            f"--auto-residual {args.auto_residual}: expected a finite number >= 1 "
            "(1: every odometry outlier)"
        )
    if not (math.isfinite(args.auto_min_speed) and args.auto_min_speed >= 0):
        raise CLIError(f"--auto-min-speed {args.auto_min_speed}: expected a finite number >= 0")
    if not (args.auto_coherence > 0):  # inf allowed: position only
        raise CLIError(f"--auto-coherence {args.auto_coherence}: expected a number > 0 (or inf)")
    if not (math.isfinite(args.steer_lead) and args.steer_lead >= 0):
        raise CLIError(f"--steer-lead {args.steer_lead}: expected a finite number of frames >= 0")
    fi = args.frame_interval
    if fi is not None and not (math.isfinite(fi) and fi > 0):
        raise CLIError(f"--frame-interval {fi}: expected a finite number of seconds > 0")
    try:
        specs = [parse_region(text) for text in args.region]
        landmarks = [parse_landmark(text) for text in args.landmark]
    except RegionError as exc:
        raise CLIError(str(exc)) from exc
    names = [spec.name for spec in specs]
    for spec in specs:
        if names.count(spec.name) > 1:
            raise CLIError(f"--region {spec.text}: the name {spec.name!r} is given twice")
    for (name, _, _), text in zip(landmarks, args.landmark, strict=True):
        if name not in names:
            known = ", ".join(names) or "none given"
            raise CLIError(f"--landmark {text}: no --region named {name!r} (regions: {known})")
        if [lm[0] for lm in landmarks].count(name) > 1:
            raise CLIError(f"--landmark {text}: region {name!r} has two landmarks")
    if len(landmarks) == 1:
        raise CLIError(
            f"--landmark {args.landmark[0]}: a position fix needs at least 2 landmarks "
            "(one fixes the position only up to a turn about it)"
        )


def region_masks(args, rig: Rig, shape: tuple[int, int]) -> list[tuple[Any, np.ndarray]]:
    """Each --region as (RegionSpec, cam1 pixel mask (H, W) bool); files read and checked."""
    from omniflow.applications.regions import RegionError, in_box, parse_region

    out = []
    labels = None
    for text in args.region:
        try:
            spec = parse_region(text, r_m=rig.cam1.r_m)
        except RegionError as exc:
            raise CLIError(str(exc)) from exc
        if spec.kind == "box":
            x, y = rig.cam1.pixel_centres()
            h1, theta = rig.cam1.polar_of_pixel(x, y)
            mask = in_box(theta, h1, spec.box) & (h1 <= rig.cam1.r_m)
        elif spec.kind == "mask":
            try:
                image = read_image(spec.path)
            except ImageError as exc:
                raise CLIError(f"--region {text}: {one_line(exc)}") from exc
            if image.shape[:2] != tuple(shape):
                raise CLIError(
                    f"--region {text}: the mask is {size_text(image.shape)}; expected cam1's size "
                    f"{size_text(shape)}"
                )
            if not np.isfinite(image).all():
                raise CLIError(f"--region {text}: the mask has NaN or infinite pixels")
            mask = image != 0 if image.ndim == 2 else np.any(image != 0, axis=2)
        else:
            if not args.dataset:
                raise CLIError(
                    f"--region {text}: object regions need --dataset (its ground truth "
                    "gt.object names the objects)"
                )
            if labels is None:
                labels, objects = _object_labels(args.dataset, args.frame)
            ident = _object_id(spec, objects, text)
            mask = labels == ident
        out.append((spec, mask))
    return out


def _object_labels(directory: str, k: int) -> tuple[np.ndarray, dict[int, str]]:
    """gt.object of cam1 at frame K of a dataset, and the dataset's id -> name table."""
    from omniflow.io.dataset import DatasetError, open_dataset

    try:
        ds = open_dataset(directory)
        labels = np.rint(ds.read_frame(k, "cam1")["gt.object"]).astype(int)
    except DatasetError as exc:
        raise CLIError(str(exc)) from exc
    return labels, ds.objects


def _object_id(spec, objects: dict[int, str], text: str) -> int:
    """The gt.object id a --region NAME:object:ID|NAME means (CLIError if none)."""
    if isinstance(spec.object, int) and spec.object in objects:
        return spec.object
    ids = [i for i, name in objects.items() if name == spec.object]
    if len(ids) == 1:
        return ids[0]
    shown = ", ".join(f"{i} {n}" for i, n in sorted(objects.items())) or "none"
    raise CLIError(
        f"--region {text}: no object {spec.object!r} in the dataset; expected an id or "
        f"name of: {shown}"
    )


def fit_odometry(cols, radial_weight: float):
    """(OdometryFit or None, its summary for flow.json) on every point's flow."""
    from omniflow.applications.navigation import odometry

    radial = cols["dr_dt"] if radial_weight > 0 else None
    rows = "dtheta/dt, r" + (f" and dr/dt (weight {radial_weight:g})" if radial is not None else "")
    try:
        fit = odometry(cols["theta"], cols["r"], cols["dtheta_dt"], radial,
                       radial_weight=radial_weight)  # fmt: skip
    except ValueError as exc:
        return None, {"error": one_line(exc)}
    return fit, {
        "fitted_on": f"{rows} of every point (omniflow.applications.navigation.odometry, robust)",
        "yaw_rate_rad_per_frame": fit.w,
        "V_x_m_per_frame": fit.V_x,
        "V_y_m_per_frame": fit.V_y,
        "inlier_fraction": fit.inlier_fraction,
        "residual_scale_m_per_frame": fit.scale,
        "inlier_threshold_m_per_frame": fit.threshold,
        "inliers": "flow.csv column odometry_inlier: 1 where the fit used the point",
    }


def region_rows(args, cols, masks, fit, rig: Rig, frame_interval, mono=None):
    """regions.csv rows, pixel outlines for the pictures, and the flow.json block.

    ``mono``: the cam1-only columns (``--monocular-gap``), summarised per given region."""
    from omniflow.applications.regions import auto_groups, in_box, points_in_mask, summarise

    rows, outlines = [], []
    for spec, mask in masks:
        if spec.kind == "box":
            member = in_box(cols["theta"], cols["h1"], spec.box)
            mono_member = None if mono is None else in_box(mono["theta"], mono["h1"], spec.box)
        else:
            member = points_in_mask(mask, cols["x"], cols["y"])
            mono_member = None if mono is None else points_in_mask(mask, mono["x"], mono["y"])
        rows.append(summarise(spec.name, spec.kind, spec.text, cols, member,
                              frame_interval=frame_interval, lead=args.steer_lead,
                              monocular=mono, monocular_member=mono_member))  # fmt: skip
        outlines.append((spec.name, mask))
    block: dict[str, Any] = {}
    if args.auto_regions:
        link = args.auto_link if args.auto_link is not None else rig.cam1.r_m / 10
        block["auto"] = {
            "found_by": "odometry residual > K x its inlier threshold and own speed > "
            "min_speed, grouped by single "
            "linkage in cam1's image (gaps <= link px, own velocities within coherence x the "
            "larger), groups >= min_points",
            "K": args.auto_residual,
            "coherence": args.auto_coherence,
            "link_px": link,
            "min_points": args.auto_min_points,
            "min_speed_m_per_frame": args.auto_min_speed,
        }
        labels = np.zeros(len(cols["x"]), dtype=int)
        if fit is None:
            block["auto"]["error"] = "no odometry fit (see odometry)"
        else:
            with np.errstate(invalid="ignore"):
                moving = np.isfinite(fit.residuals) & (
                    fit.residuals > args.auto_residual * fit.threshold
                )
            own = fit.own_velocity(cols["theta"], cols["r"], cols["dr_dt"], cols["dtheta_dt"])
            with np.errstate(invalid="ignore"):
                moving &= np.hypot(own[:, 0], own[:, 1]) > args.auto_min_speed
            labels = auto_groups(cols["x"], cols["y"], moving, link=link,
                                 min_points=args.auto_min_points, velocity=own,
                                 coherence=args.auto_coherence)  # fmt: skip
            block["auto"]["candidates"] = int(moving.sum())
        cols["auto_region"] = labels.astype(float)
        for k in range(1, int(labels.max(initial=0)) + 1):
            member = labels == k
            v = np.median(own[member], axis=0)
            spec = f"auto: own velocity ({v[0]:.3g}, {v[1]:.3g}) m/frame (rig X, Y, median)"
            rows.append(summarise(f"auto{k}", "auto", spec, cols, member,
                                  frame_interval=frame_interval, lead=args.steer_lead))  # fmt: skip
            outlines.append((f"auto{k}", _hull_mask(cols["x"][member], cols["y"][member], rig)))
    for row in rows:
        if row["points"] == 0 and not row["monocular_points"] > 0:
            warnings.warn(f"region {row['name']} ({row['spec']}) holds no matched point; "
                          "its row in regions.csv is empty", stacklevel=2)  # fmt: skip
    block.update({
        "file": "regions.csv",
        "frame_interval_s": frame_interval,
        "steer_lead_frames": args.steer_lead,
        "rows": rows,
    })  # fmt: skip
    return rows, outlines, block


def _hull_mask(x: np.ndarray, y: np.ndarray, rig: Rig) -> np.ndarray:
    """cam1 pixel mask of the convex hull of points (for the pictures)."""
    import cv2

    mask = np.zeros((rig.cam1.height, rig.cam1.width), np.uint8)
    pts = np.column_stack([np.floor(x), np.floor(y)]).astype(np.int32)
    cv2.fillConvexPoly(mask, cv2.convexHull(pts), 1)
    return mask.astype(bool)


def position_fix_block(args, rows) -> dict:
    """The robot's pose from --landmark regions (omniflow.applications.navigation.position_fix)."""
    from omniflow.applications.navigation import position_fix
    from omniflow.applications.regions import parse_landmark

    by_name = {row["name"]: row for row in rows}
    marks = [parse_landmark(text) for text in args.landmark]
    used = [(name, x, y, by_name[name]) for name, x, y in marks]
    empty = [name for name, _, _, row in used if row["points"] == 0]
    block: dict[str, Any] = {"landmarks": {n: [x, y] for n, x, y, _ in used}}
    if empty:
        block["error"] = f"region(s) {', '.join(empty)} hold no matched point"
        return block
    try:
        fix = position_fix(
            [[x, y] for _, x, y, _ in used],
            [row["r"] for *_, row in used],
            [math.radians(row["bearing_deg"]) for *_, row in used],
        )
    except ValueError as exc:
        block["error"] = one_line(exc)
        return block
    block.update({
        "from": "each region's centroid (r, bearing) against its landmark's world (X, Y)",
        "x_m": fix.x,
        "y_m": fix.y,
        "yaw_deg": math.degrees(fix.yaw),
        "rms_position_m": fix.rms_position,
    })  # fmt: skip
    return block
