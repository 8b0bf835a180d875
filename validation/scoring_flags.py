"""Flagged points: where a method says eq. (14) fails, scored apart, and the flag against the truth.

The paper's method ties cam2's radial flow to cam1's, dh_2 = (h_2 / h_1) dh_1
(eq. 14), which holds only for a point that does not move along the axis. omniflow
flags the points where its two-model test rejects eq. (14) (result column
``coupled`` = 0, :mod:`omniflow.solve.decoupled`); they are not confident answers.
The harness scores the flagged and the unflagged points of each camera apart
(point sets ``flagged`` and ``unflagged`` beside ``own``) and compares the flag
with the truth: a point **breaks eq. (14)** where the violation that its true
axial motion causes, s v dh / ((d + r)(s - h)) px per frame
(:func:`omniflow.paper.flow.axial_motion_violation`), is at least :data:`BREAK_PX`.
Its dh is the material point's motion along the axis from frame t to t + 1 in
the rig frame (:func:`validation.motion.point_motion`, from the poses in
``dataset.json``): a static wall seen by a robot driving on the floor has dh = 0,
every point of a rig moving up and down breaks it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.paper.flow import axial_motion_violation

from .motion import point_motion
from .results import Results
from .sampling import sample_truth
from .scoring_flow import omniflow_points, score_flow
from .scoring_stereo import STEREO_TRUTH

__all__ = ["BREAK_PX", "FLAG_SETS", "flag_counts", "flagged", "score_flags"]

#: A point breaks eq. (14) where its true violation is at least this, px per frame: a
#: tenth of a pixel, several times the default's own endpoint error on the library
#: scenes, so a smaller violation hides in it (docs/decisions/eq14_flag.md).
BREAK_PX = 0.1
#: The point sets :func:`score_flags` fills beside ``own``.
FLAG_SETS = ("unflagged", "flagged")


def flagged(cols: dict[str, NDArray]) -> NDArray | None:
    """Which points the method flags (``coupled`` = 0); None where it has no such column."""
    if "coupled" not in cols:
        return None
    return np.asarray(cols["coupled"], dtype=np.float64) < 0.5


def score_flags(
    results: Results,
    name: str,
    cols: dict[str, NDArray],
    truth: dict[str, dict[str, NDArray]],
    t: int,
    rig: Any,
    robot_poses: list | None,
    object_poses: dict[int, list],
) -> dict[str, Any]:
    """Score one row's flagged and unflagged points apart and its flag against the truth.

    Fills ``results.flow[(name, "flagged" | "unflagged", cam)]`` and appends one record
    to ``results.flags[name]`` (``flagged``, ``breaks`` and ``violation`` at the cam1
    points with truth; ``breaks`` all False where the dataset has no poses). Returns the
    per-frame row's ``flagged_share``, ``flag_precision`` and ``flag_recall``; nothing
    for a row without a ``coupled`` column.
    """
    flag = flagged(cols)
    if flag is None:
        return {}
    for cam in ("cam1", "cam2"):
        x, y, est = omniflow_points(cols, cam)
        for label, sel in zip(FLAG_SETS, (~flag, flag), strict=True):
            sub = {k: v[sel] for k, v in est.items()}
            results.flow[(name, label, cam)].append(score_flow(sub, x[sel], y[sel], truth[cam]))
    x, y, _ = omniflow_points(cols, "cam1")
    tr = sample_truth(truth["cam1"], x, y, channels=STEREO_TRUTH)
    has = tr["bilinear_ok"] & (tr["gt.valid"] > 0.5)
    violation = np.zeros(int(has.sum()))
    known = robot_poses is not None and len(robot_poses) > t + 1
    if known:
        world = np.stack([tr["gt.X"], tr["gt.Y"], tr["gt.Z"]], axis=1)[has]
        ids = np.rint(tr["gt.object"][has]).astype(np.int64)
        poses_t = {k: v[t] for k, v in object_poses.items() if len(v) > t + 1}
        poses_t1 = {k: v[t + 1] for k, v in object_poses.items() if len(v) > t + 1}
        mot = point_motion(world, ids, poses_t, poses_t1, robot_poses[t], robot_poses[t + 1])
        violation = axial_motion_violation(tr["gt.r"][has], tr["gt.h"][has], mot["dh_dt"],
                                           s=rig.s, d=rig.d, v=rig.cam1.v)  # fmt: skip
    rec = {
        "flagged": flag[has],
        "breaks": np.abs(violation) >= BREAK_PX,
        "violation": violation,
        "object": tr["gt.object"][has],
        "truth_known": known,
    }
    results.flags[name].append(rec)
    c = flag_counts([rec])
    return {"flagged_share": c["share_flagged"], "flag_precision": c["precision"],
            "flag_recall": c["recall"]}  # fmt: skip


def flag_counts(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The flag over the points of ``records`` pooled: how many, what share, and against
    the truth (``precision``: breakers among the flagged; ``recall``: flagged among the
    breakers; NaN where undefined or where a frame has no poses)."""
    fl = np.concatenate([np.asarray(r["flagged"], bool) for r in records]) if records else []
    br = np.concatenate([np.asarray(r["breaks"], bool) for r in records]) if records else []
    fl, br = np.asarray(fl, bool), np.asarray(br, bool)
    known = bool(records) and all(r["truth_known"] for r in records)
    n, nf, nb, both = fl.size, int(fl.sum()), int(br.sum()), int((fl & br).sum())
    return {
        "n_points": int(n),
        "n_flagged": nf,
        "share_flagged": nf / n if n else math.nan,
        "n_breaks": nb if known else None,
        "n_flagged_breaks": both if known else None,
        "precision": both / nf if known and nf else math.nan,
        "recall": both / nb if known and nb else math.nan,
        "break_px": BREAK_PX,
    }
