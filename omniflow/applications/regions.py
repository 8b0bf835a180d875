"""Regions of an omni flow result: which points belong to an object, and its summary.

A region is a set of the matched points of one frame pair, named by the user
or found automatically, over which section 6 of the paper averages the flow
(:func:`omniflow.applications.navigation.region_flow`) to get the object's radial
velocity, time to contact and a steering heading. This module turns the
``omniflow`` command's region options into point memberships and rows:

- :func:`parse_region` reads ``NAME:box:THETA0,THETA1,H0,H1`` (a box in cam1's
  polar image coordinates, degrees and pixels), ``NAME:mask:FILE`` (an image,
  non-zero inside) and ``NAME:object:ID|NAME`` (an object of an omnisim
  dataset's ground truth ``gt.object``);
- :func:`in_box` tests polar points against a box (wrapping through 360 deg);
- :func:`points_in_mask` looks points up in a per-pixel mask;
- :func:`auto_groups` groups the points whose flow the robot's own motion does
  not explain (odometry's outliers) into spatially connected groups, the
  independently moving objects;
- :func:`summarise` computes one region's row of ``regions.csv``
  (:data:`REGION_COLUMNS`);
- :func:`draw_regions` outlines the regions on a picture.

Errors in the user's region text raise :class:`RegionError` with a one-line
message naming the ``--region`` value and what was expected.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "REGION_COLUMNS",
    "RegionError",
    "RegionSpec",
    "auto_groups",
    "draw_regions",
    "in_box",
    "parse_landmark",
    "parse_region",
    "points_in_mask",
    "regions_csv_text",
    "summarise",
]

#: Columns of ``regions.csv``, in order, with their units.
REGION_COLUMNS: dict[str, str] = {
    "name": "the region's name (auto1, auto2, ... for automatic groups, largest first)",
    "kind": "box, mask, object or auto",
    "spec": "the region as given (or how the group was found)",
    "points": "matched points in the region",
    "dh1_dt": "px/frame, mean cam1 radial flow",
    "dtheta_dt": "rad/frame, mean angular flow",
    "dx": "px/frame, mean cam1 flow along x",
    "dy": "px/frame, mean cam1 flow along y",
    "dr_dt_mean": "m/frame, mean of the points' dr/dt",
    "r": "m, range of the region's centroid (floor plane)",
    "bearing_deg": "deg, azimuth theta of the centroid, in [-180, 180)",
    "dr_dt": "m/frame, radial velocity of the centroid from the mean relative velocity",
    "time_to_contact_frames": "frames, -r / dr_dt of the centroid; inf (empty) if not closing",
    "time_to_contact_s": "s, time_to_contact_frames x the frame interval (empty if unknown)",
    "time_to_contact_median_frames": "frames, median of the points' -r / (dr/dt)",
    "steer_home_in_deg": "deg, heading towards the centroid extrapolated --steer-lead frames",
    "steer_avoid_deg": "deg, heading straight away from that point",
    "monocular_points": "cam1-only points in the region (--monocular-gap; empty without it)",
    "monocular_bearing_deg": "deg, circular mean azimuth of those points, in [-180, 180)",
    "monocular_dtheta_dt": "rad/frame, their mean angular flow: the region's bearing rate",
    "monocular_dh1_dt": "px/frame, their mean cam1 radial flow (weakly determined by cam1 alone)",
}

_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")
_KINDS = ("box", "mask", "object")
_FORMS = "NAME:box:THETA0,THETA1,H0,H1, NAME:mask:FILE or NAME:object:ID|NAME"


class RegionError(ValueError):
    """A region or landmark option that cannot be used; the message names it."""


@dataclass(frozen=True)
class RegionSpec:
    """A region as the user gave it.

    Attributes
    ----------
    name : str
        Letters, digits, ``_ . -``; unique; ``auto...`` is reserved.
    kind : {"box", "mask", "object"}
    text : str
        The option's value, for messages and the outputs.
    box : (float, float, float, float) or None
        ``(theta0, theta1, h0, h1)``: degrees, degrees, pixels, pixels.
    path : str or None
        The mask image (kind ``mask``).
    object : int or str or None
        The object id or name (kind ``object``).
    """

    name: str
    kind: str
    text: str
    box: tuple[float, float, float, float] | None = None
    path: str | None = None
    object: int | str | None = None


def _numbers(text: str, count: int, what: str, flag: str, raw: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise RegionError(f"{flag} {raw}: expected {what} ({count} finite numbers)")
    return values


def parse_region(text: str, *, r_m: float | None = None) -> RegionSpec:
    """Read one ``--region`` value.

    Forms: ``NAME:box:THETA0,THETA1,H0,H1`` (theta in degrees, the box running
    from THETA0 in the direction of increasing theta to THETA1, through 360
    when THETA1 < THETA0: ``350,10`` is 20 degrees wide; image radius h1 in
    cam1 pixels, ``0 <= H0 < H1 <= r_m``), ``NAME:mask:FILE`` and
    ``NAME:object:ID|NAME``.

    Parameters
    ----------
    text : str
        The option's value.
    r_m : float, optional
        cam1's rim radius in pixels: the largest H1 a box may have.

    Raises
    ------
    RegionError
        Naming the value and what was expected.
    """
    flag = "--region"
    parts = text.split(":", 2)
    if len(parts) != 3 or not parts[2]:
        raise RegionError(f"{flag} {text}: expected {_FORMS}")
    name, kind, rest = parts
    if not _NAME_RE.match(name):
        raise RegionError(f"{flag} {text}: the name {name!r}: expected letters, digits, _ . -")
    if name.lower().startswith("auto"):
        raise RegionError(f"{flag} {text}: names starting 'auto' are the automatic groups'")
    if kind not in _KINDS:
        raise RegionError(f"{flag} {text}: kind {kind!r}: expected one of {', '.join(_KINDS)}")
    if kind == "mask":
        return RegionSpec(name, kind, text, path=rest)
    if kind == "object":
        obj: int | str = int(rest) if re.fullmatch(r"\d+", rest) else rest
        return RegionSpec(name, kind, text, object=obj)
    t0, t1, h0, h1 = _numbers(rest, 4, "THETA0,THETA1,H0,H1 (deg, deg, px, px)", flag, text)
    for v in (t0, t1):
        if not -360.0 <= v <= 360.0:
            raise RegionError(f"{flag} {text}: theta {v:g}: expected degrees in [-360, 360]")
    span = t1 - t0
    if span != 360.0 and (span % 360.0) == 0.0:
        raise RegionError(
            f"{flag} {text}: THETA0 = THETA1 (mod 360) is an empty box; "
            "expected a range (THETA1 = THETA0 + 360 for the full circle)"
        )
    top = f"{r_m:g} (cam1's rim radius r_m)" if r_m is not None else "the rim radius"
    if not (0.0 <= h0 < h1) or (r_m is not None and h1 > r_m):
        raise RegionError(
            f"{flag} {text}: h1 range {h0:g}..{h1:g} px: expected 0 <= H0 < H1 <= {top}"
        )
    return RegionSpec(name, kind, text, box=(t0, t1, h0, h1))


def parse_landmark(text: str) -> tuple[str, float, float]:
    """Read one ``--landmark NAME:X,Y`` value: a region name and its world position (m)."""
    name, sep, rest = text.partition(":")
    if not sep or not _NAME_RE.match(name):
        raise RegionError(f"--landmark {text}: expected NAME:X,Y (a region's name, world metres)")
    x, y = _numbers(rest, 2, "NAME:X,Y (world metres)", "--landmark", text)
    return name, x, y


def in_box(theta: ArrayLike, h1: ArrayLike, box: tuple[float, float, float, float]) -> NDArray:
    """Which polar points (theta in radians, h1 in pixels) lie in a box.

    ``box = (theta0, theta1, h0, h1)`` as :func:`parse_region` reads it: the
    azimuths from theta0 to theta1 degrees in the direction of increasing
    theta (through 360 if theta1 < theta0), both ends included.
    """
    t0, t1, lo, hi = box
    span = t1 - t0
    span = 360.0 if span == 360.0 else span % 360.0
    theta_deg = np.degrees(np.asarray(theta, dtype=float))
    offset = np.mod(theta_deg - t0, 360.0)
    h = np.asarray(h1, dtype=float)
    return (offset <= span) & (h >= lo) & (h <= hi)


def points_in_mask(mask: NDArray, x: ArrayLike, y: ArrayLike) -> NDArray:
    """``mask`` (H, W bool) at continuous pixel points (pixel (i, j) spans x in [j, j + 1))."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    h, w = mask.shape
    ok = np.isfinite(x) & np.isfinite(y)
    j = np.floor(np.where(ok, x, -1)).astype(int)
    i = np.floor(np.where(ok, y, -1)).astype(int)
    ok &= (i >= 0) & (i < h) & (j >= 0) & (j < w)
    out = np.zeros(x.shape, dtype=bool)
    out[ok] = mask[i[ok], j[ok]]
    return out


def auto_groups(
    x: ArrayLike,
    y: ArrayLike,
    candidate: ArrayLike,
    *,
    link: float,
    min_points: int,
    velocity: ArrayLike | None = None,
    coherence: float = math.inf,
) -> NDArray:
    """Connected groups of candidate points: (N,) labels, 0 = in no group.

    Two candidates are neighbours when they lie at most ``link`` pixels apart
    in cam1's image and, given ``velocity`` (N, 2), their velocities differ by
    at most ``coherence`` times the larger of the two (the points of one
    object moving on its own share its velocity; mismatched static points
    scatter). A group is a chain of neighbours (single linkage:
    :meth:`scipy.spatial.cKDTree.query_pairs` and
    :func:`scipy.sparse.csgraph.connected_components`). Groups of fewer than
    ``min_points`` points are dropped; the rest are numbered 1, 2, ... from
    the largest.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    cand = np.asarray(candidate, dtype=bool) & np.isfinite(x) & np.isfinite(y)
    if velocity is not None:
        v = np.asarray(velocity, dtype=float).reshape(-1, 2)
        cand &= np.isfinite(v).all(axis=1)
    labels = np.zeros(x.shape, dtype=int)
    idx = np.flatnonzero(cand)
    if idx.size == 0:
        return labels
    pts = np.column_stack([x[idx], y[idx]])
    pairs = cKDTree(pts).query_pairs(float(link), output_type="ndarray")
    if velocity is not None and math.isfinite(coherence):
        va, vb = v[idx[pairs[:, 0]]], v[idx[pairs[:, 1]]]
        larger = np.maximum(np.hypot(*va.T), np.hypot(*vb.T))
        pairs = pairs[np.hypot(*(va - vb).T) <= coherence * larger]
    graph = coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(idx.size, idx.size)
    )
    _, comp = connected_components(graph, directed=False)
    sizes = np.bincount(comp)
    order = np.argsort(-sizes, kind="stable")
    number = 0
    for c in order:
        if sizes[c] < min_points:
            break
        number += 1
        labels[idx[comp == c]] = number
    return labels


def summarise(
    name: str,
    kind: str,
    spec: str,
    cols: dict[str, NDArray],
    member: NDArray,
    *,
    frame_interval: float | None,
    lead: float = 1.0,
    monocular: dict[str, NDArray] | None = None,
    monocular_member: NDArray | None = None,
) -> dict[str, Any]:
    """One region's row of ``regions.csv`` (:data:`REGION_COLUMNS`).

    The mean flow of the points with finite values, their mean dr/dt, and the
    centroid's range, bearing, radial velocity and time to contact from
    :func:`omniflow.applications.navigation.region_flow`, the steering headings from
    :func:`omniflow.applications.navigation.steering_heading` (``lead`` frames ahead).
    A region without usable points gets 0 points and NaN elsewhere.

    ``monocular`` (the cam1-only columns of :mod:`omniflow.solve.monocular`) and
    ``monocular_member`` (which of them lie in the region) add the
    ``monocular_*`` columns: the bearing and bearing rate of an object the rig
    cannot range (no range, so no dr/dt or time to contact from them). Without
    them those columns are NaN (written empty).
    """
    from omniflow.applications.navigation import region_flow, steering_heading, time_to_contact

    row: dict[str, Any] = {"name": name, "kind": kind, "spec": spec}
    member = np.asarray(member, dtype=bool)
    keys = ("theta", "r", "dr_dt", "dtheta_dt", "dh1_dt", "dx", "dy")
    ok = member & np.all([np.isfinite(cols[k]) for k in keys], axis=0)
    row["points"] = int(ok.sum())
    for key in REGION_COLUMNS:
        if key not in row:
            row[key] = math.nan
    if monocular is not None and monocular_member is not None:
        _monocular_columns(row, monocular, np.asarray(monocular_member, dtype=bool))
    if not ok.any():
        return row
    for key in ("dh1_dt", "dtheta_dt", "dx", "dy"):
        row[key] = float(np.mean(cols[key][ok]))
    row["dr_dt_mean"] = float(np.mean(cols["dr_dt"][ok]))
    rf = region_flow(cols["theta"], cols["r"], cols["dr_dt"], cols["dtheta_dt"], mask=ok)
    row["r"] = rf.r
    row["bearing_deg"] = math.degrees(rf.theta)
    row["dr_dt"] = rf.dr_dt
    row["time_to_contact_frames"] = rf.time_to_contact
    if frame_interval is not None:
        row["time_to_contact_s"] = rf.time_to_contact * frame_interval
    row["time_to_contact_median_frames"] = float(
        np.median(time_to_contact(cols["r"][ok], cols["dr_dt"][ok]))
    )
    row["steer_home_in_deg"] = math.degrees(steering_heading(rf, mode="home_in", lead=lead))
    row["steer_avoid_deg"] = math.degrees(steering_heading(rf, mode="avoid", lead=lead))
    return row


def _monocular_columns(row: dict[str, Any], mono: dict[str, NDArray], member: NDArray) -> None:
    """Fill the ``monocular_*`` columns of one row from the cam1-only points in it."""
    ok = member & np.isfinite(mono["dtheta_dt"]) & np.isfinite(mono["dh1_dt"])
    row["monocular_points"] = int(ok.sum())
    if ok.any():
        mean_dir = np.mean(np.exp(1j * mono["theta"][ok]))
        row["monocular_bearing_deg"] = (
            math.degrees(float(np.angle(mean_dir))) + 180.0
        ) % 360.0 - 180.0
        row["monocular_dtheta_dt"] = float(np.mean(mono["dtheta_dt"][ok]))
        row["monocular_dh1_dt"] = float(np.mean(mono["dh1_dt"][ok]))


def regions_csv_text(rows: list[dict[str, Any]]) -> str:
    """``regions.csv``: a '#' line of units, a header, one row per region.

    Non-finite numbers (no point, not closing) are written as empty fields.
    """
    import csv
    import io

    buf = io.StringIO()
    units = "; ".join(f"{k}: {v}" for k, v in REGION_COLUMNS.items())
    buf.write(f"# omniflow regions; {units}\n")
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(REGION_COLUMNS)
    for row in rows:
        cells = []
        for key in REGION_COLUMNS:
            v = row[key]
            if isinstance(v, float):
                v = f"{v:.9g}" if math.isfinite(v) else ""
            cells.append(v)
        writer.writerow(cells)
    return buf.getvalue()


#: Outline colours (RGB) of the regions in the pictures, in turn.
_COLOURS = ((255, 64, 255), (64, 255, 255), (255, 255, 64), (255, 128, 0), (128, 255, 0))


def draw_regions(canvas: NDArray[np.uint8], outlines: list[tuple[str, NDArray]]) -> None:
    """Outline each region's pixel mask on an RGB picture and write its name beside it.

    ``outlines``: (name, (H, W) bool mask) pairs; the canvas is changed in place.
    """
    import cv2

    h, w = canvas.shape[:2]
    font = max(0.35, h / 1200.0)
    face = cv2.FONT_HERSHEY_SIMPLEX
    placed: list[tuple[int, int, int, int]] = []  # label boxes so far (x0, y0, x1, y1)
    for k, (name, mask) in enumerate(outlines):
        colour = _COLOURS[k % len(_COLOURS)]
        contours, _ = cv2.findContours(
            mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
        )
        if not contours:
            continue
        cv2.drawContours(canvas, contours, -1, colour, 1, cv2.LINE_AA)
        # The name at the mask's centroid, kept inside the picture.
        i, j = np.nonzero(mask)
        (tw, th), _ = cv2.getTextSize(name, face, font, 1)
        cx = int(np.clip(j.mean() - tw / 2, 0, max(0, w - tw)))
        cy = int(np.clip(i.mean() + th / 2, th, h - 2))
        for _ in range(len(placed)):  # move down past labels it would overlap
            hit = [
                b for b in placed if cx < b[2] and b[0] < cx + tw and cy - th < b[3] and b[1] < cy
            ]
            if not hit:
                break
            cy = max(b[3] for b in hit) + th + 3
        cy = int(min(cy, h - 2))
        placed.append((cx - 6, cy - th - 2, cx + tw + 6, cy + 3))  # with a margin
        cv2.putText(canvas, name, (cx, cy), face, font, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(canvas, name, (cx, cy), face, font, colour, 1, cv2.LINE_AA)
