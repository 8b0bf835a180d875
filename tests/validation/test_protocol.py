"""validation: the benchmark protocol's metrics (epe, 1px, fl, wauc and their splits) against
hand-computed values, and the dense interpolation of a sparse flow.

Every expected value is worked out in the comment beside it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from validation.densify import MIN_POINTS, interpolate_flow
from validation.metrics import (
    PROTOCOL_RANGE_BINS,
    PROTOCOL_SPEED_BINS,
    WAUC_WEIGHTS,
    fl_rate,
    outlier_rate,
    protocol_metrics,
    protocol_splits,
    wauc,
)

EPE = np.array([0.0, 0.5, 1.0, 1.5, 4.0, 4.0])
SPEED = np.array([10.0, 10.0, 10.0, 10.0, 100.0, 10.0])


def test_outlier_rate_counts_strictly_above_one_pixel():
    # 1.5 and the two 4.0 are > 1; 1.0 is not: 3 of 6.
    assert outlier_rate(EPE) == pytest.approx(0.5)
    assert outlier_rate([np.nan, 2.0]) == 1.0  # the NaN is left out, not counted as good
    assert math.isnan(outlier_rate([]))


def test_fl_needs_three_pixels_and_five_percent():
    # Point 5: 4 > 3 but 4 < 0.05 x 100 = 5, not an Fl outlier; point 6: 4 > 3 and
    # 4 > 0.05 x 10 = 0.5, an outlier. 1 of 6.
    assert fl_rate(EPE, SPEED) == pytest.approx(1 / 6)
    assert fl_rate([3.0], [1.0]) == 0.0  # 3 px is not > 3 px
    assert math.isnan(fl_rate([np.nan], [1.0]))


def test_wauc_hand_values():
    # EPE 0: within every threshold, a_i = 1 for all i: WAUC 1.
    assert wauc([0.0]) == pytest.approx(1.0)
    # EPE 10 px: beyond 5 px, a_i = 0: WAUC 0.
    assert wauc([10.0]) == 0.0
    # EPE 2.52 px: within delta_i = 0.05 i for i >= 51. w_i = (101 - i) / 100, so
    # sum_{i=51..100} w_i = (1 + ... + 50) / 100 = 12.75 and sum_{i=1..100} w_i = 50.5.
    assert WAUC_WEIGHTS.sum() == pytest.approx(50.5)
    assert wauc([2.52]) == pytest.approx(12.75 / 50.5)
    # Two points, 0 and 10 px: a_i = 1/2 everywhere: WAUC 0.5.
    assert wauc([0.0, 10.0]) == pytest.approx(0.5)
    assert math.isnan(wauc([]))


def test_protocol_metrics_hand_values():
    m = protocol_metrics(EPE, SPEED)
    assert m["n"] == 6
    assert m["epe"] == pytest.approx(11 / 6)  # (0 + 0.5 + 1 + 1.5 + 4 + 4) / 6
    assert m["1px"] == pytest.approx(0.5)
    assert m["fl"] == pytest.approx(1 / 6)
    empty = protocol_metrics([], [])
    assert empty["n"] == 0 and math.isnan(empty["epe"]) and math.isnan(empty["wauc"])


def test_protocol_splits_name_each_point_once():
    err = {
        "epe": np.array([0.0, 2.0, 0.5, 3.5, 1.5]),
        "speed": np.array([0.2, 0.7, 1.5, 5.0, 9.0]),
        "noc": np.array([True, True, False, False, True]),
        "outside": np.array([False, False, False, True, False]),
        "range": np.array([0.5, 1.5, 3.0, 10.0, 20.0]),
        "object": np.array([1.0, 1.0, 2.0, 2.0, 3.0]),
    }
    s = protocol_splits(err, moving=[2])
    assert s["all"]["n"] == 5 and s["all"]["1px"] == pytest.approx(3 / 5)  # 2.0, 3.5, 1.5
    # matched: points 0, 1, 4 (EPE 0, 2, 1.5): 2 of 3 above 1 px.
    assert s["region"]["matched"]["n"] == 3
    assert s["region"]["matched"]["1px"] == pytest.approx(2 / 3)
    # occluded: point 2 (not matched, not outside); outside: point 3.
    assert s["region"]["occluded"]["n"] == 1 and s["region"]["occluded"]["epe"] == 0.5
    assert s["region"]["outside"]["n"] == 1 and s["region"]["outside"]["epe"] == 3.5
    # moving: object 2 = points 2, 3 (EPE 0.5, 3.5): mean 2.0; static: objects 1 and 3.
    assert s["rigid"]["moving"]["epe"] == pytest.approx(2.0)
    assert s["rigid"]["static"]["n"] == 3
    # Point 3: EPE 3.5 > 3 and > 0.05 x 5.0: Fl 1 in the moving split.
    assert s["rigid"]["moving"]["fl"] == pytest.approx(0.5)
    # One point per speed bin 0-0.5, 0.5-1, 1-2, 4-8, >=8 and none in 2-4.
    assert [b["n"] for b in s["speed"].values()] == [1, 1, 1, 0, 1, 1]
    assert list(s["speed"]) == ["0-0.5px", "0.5-1px", "1-2px", "2-4px", "4-8px", ">=8px"]
    assert len(s["speed"]) == len(PROTOCOL_SPEED_BINS) - 1
    # Ranges 0.5, 1.5, 3, 10, 20 m: bins 0-1, 1-2, 2-4, 8-16, >=16; none in 4-8.
    assert [b["n"] for b in s["range"].values()] == [1, 1, 1, 0, 1, 1]
    assert len(s["range"]) == len(PROTOCOL_RANGE_BINS) - 1


def test_protocol_splits_without_outside_channel():
    """A format-1 dataset has no gt.flow.outside: every unmatched point is occluded."""
    err = {"epe": np.array([1.0, 2.0]), "speed": np.ones(2), "noc": np.array([True, False]),
           "range": np.ones(2), "object": np.ones(2)}  # fmt: skip
    s = protocol_splits(err)
    assert s["region"]["occluded"]["n"] == 1 and s["region"]["outside"]["n"] == 0


def _affine_scene(h=128, w=128):
    """A textured image and a closed-form affine flow (a 0.02 rad turn about the centre
    and a (0.7, -0.3) px shift), exact at any point."""
    import cv2

    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.uint8), (0, 0), 1.5)
    a, c = 0.02, w / 2

    def flow(x, y):
        fx = np.cos(a) * (x - c) - np.sin(a) * (y - c) + c - x + 0.7
        fy = np.sin(a) * (x - c) + np.cos(a) * (y - c) + c - y - 0.3
        return fx, fy

    return img, flow, rng


def test_interpolating_the_true_flow_at_true_points_scores_near_zero():
    from validation.scoring_flow import score_dense

    img, flow, rng = _affine_scene()
    h, w = img.shape
    x, y = rng.uniform(0, w, 500), rng.uniform(0, h, 500)
    dense = interpolate_flow(img, x, y, *flow(x, y))
    assert dense.shape == (h, w, 2) and dense.dtype == np.float32
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    gdx, gdy = flow(xx, yy)
    zeros = np.zeros((h, w))
    truth = {"gt.valid": np.ones((h, w)), "gt.flow.valid": np.ones((h, w)),
             "gt.flow.dx": gdx, "gt.flow.dy": gdy, "gt.flow.dh": zeros,
             "gt.flow.hdtheta": zeros, "gt.r": np.ones((h, w)), "gt.object": np.ones((h, w)),
             "gt.stereo.valid": np.ones((h, w)), "_centre": (w / 2, h / 2)}  # fmt: skip
    err = score_dense(None, truth, dense)
    m = protocol_metrics(err["epe"], err["speed"])
    # Measured: mean EPE 6e-6 px, 99th percentile 3e-5 px (float32 output). The bound
    # 1e-3 px is far below the 0.04 px that OpenCV's smoothing post-pass adds on this
    # field, so the test also fails if that pass were switched on.
    assert m["n"] == h * w
    assert m["epe"] < 1e-3
    assert m["1px"] == 0.0 and m["fl"] == 0.0
    assert m["wauc"] == pytest.approx(1.0)


def test_interpolation_needs_a_few_points():
    img, flow, rng = _affine_scene(32, 32)
    x, y = rng.uniform(0, 32, MIN_POINTS - 1), rng.uniform(0, 32, MIN_POINTS - 1)
    assert np.isnan(interpolate_flow(img, x, y, *flow(x, y))).all()
    # Points with a NaN flow or outside the image do not count.
    x = np.r_[rng.uniform(0, 32, MIN_POINTS), 40.0]
    y = np.r_[rng.uniform(0, 32, MIN_POINTS), 5.0]
    dx, dy = flow(x, y)
    dx[0] = np.nan
    assert np.isnan(interpolate_flow(img, x, y, dx, dy)).all()
    with pytest.raises(ValueError, match="uint8"):
        interpolate_flow(img.astype(np.float32), x, y, dx, dy)
