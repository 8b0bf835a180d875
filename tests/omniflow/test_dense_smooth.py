"""The densification's smooth-profile test (``dense_smooth``,
omniflow.matching.dense.smooth_profiles).

On the rendered low_texture scene the dense preset's stereo outliers were 2.9 %: 48 of
its 65 wrong densified matches lay on a plain wall, grown from seven edge matches that
were themselves 13-15 px off, with image-1 profiles that correlate above 0.9 with
themselves half a profile radius away (a ramp over the profile's length): the 48 were
all of low_texture's densified matches that smooth (docs/decisions/dense_mode.md).
These tests build the mechanism on closed-form tables: a textured
section and a linear ramp section, image 2 the same shifted by 4 columns, seeds right on
the texture and 6 columns off on the ramp.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from omniflow.config import DENSE, OmniFlowConfig
from omniflow.matching.dense import densify, smooth_profiles

W, STRIDE, PAD, SHIFT = 8, 1, 10, 4  # profile half-length, spacing, table padding, disparity
RAMP_FROM = 130  # table columns >= this: the ramp (< it: the texture)


def _tables(seed: int = 0):
    """Tables of 6 lines and 240 columns: smoothed noise below RAMP_FROM, a linear ramp
    above; image 2 the same SHIFT columns to the right; noise 0.003 on both."""
    rng = np.random.default_rng(seed)
    n_theta, n_cols = 6, 240
    x = np.arange(n_cols + 20, dtype=float)
    tex = np.convolve(rng.standard_normal(x.size), np.ones(3) / 3, "same")
    base = np.where(x - 10 < RAMP_FROM, tex, 0.004 * (x - 10 - RAMP_FROM))
    t1 = np.tile(base[10 : 10 + n_cols], (n_theta, 1)).astype(np.float32)
    t2 = np.tile(base[10 - SHIFT : 10 - SHIFT + n_cols], (n_theta, 1)).astype(np.float32)
    t1 += 0.003 * rng.standard_normal(t1.shape).astype(np.float32)
    t2 += 0.003 * rng.standard_normal(t2.shape).astype(np.float32)
    return t1, t2


def test_smooth_profiles_flags_a_ramp_not_a_texture():
    t1, _ = _tables()
    k = np.zeros(4, dtype=np.int64)
    j = np.array([60, 100, 180, 200])  # texture, texture, ramp, ramp
    got = smooth_profiles(t1, k, j, w=W, stride=STRIDE, smooth=0.95)
    assert got.tolist() == [False, False, True, True]
    # a column where only one side's shifted profile fits uses that side (the ramp
    # section is continued to the right edge of the table: its left side is tried)
    edge = t1.shape[1] - 1 - W * STRIDE - 1
    assert smooth_profiles(t1, k[:1], np.array([edge]), w=W, stride=STRIDE,
                           smooth=0.95).tolist() == [True]  # fmt: skip
    # neither side fits: not smooth (nothing to compare)
    tiny = t1[:, : 2 * W * STRIDE + 3]
    assert smooth_profiles(tiny, k[:1], np.array([W * STRIDE + 1]), w=W, stride=STRIDE,
                           smooth=0.95).tolist() == [False]  # fmt: skip
    assert smooth_profiles(t1, k[:0], j[:0], w=W, stride=STRIDE, smooth=0.95).size == 0


def test_densify_drops_ramp_matches_a_wrong_seed_placed():
    """Without the test the ramp's 172 densified matches follow the wrong seeds (errors
    near 6 columns at NCC >= 0.9); with ``smooth`` 0.95 none is left, and the 192
    textured ones are the same (largest error 0.14 column). Measured with this seed."""
    t1, t2 = _tables()
    fh1 = np.gradient(t1, axis=1)
    tab = SimpleNamespace(pad=PAD, n_h=t1.shape[1] - 2 * PAD)
    k = np.tile(np.arange(6), 2)
    j = np.repeat([50, 180], 6) - PAD
    c2 = j + np.repeat([SHIFT, SHIFT + 6], 6).astype(float)  # the ramp's seeds 6 columns off
    kw = dict(w=W, stride=STRIDE, min_score=0.9, reach=16, flatness=0.0)
    off = densify(tab, fh1, t1, t2, (k, j, c2), 0.0, smooth=1.0, **kw)
    on = densify(tab, fh1, t1, t2, (k, j, c2), 0.0, smooth=0.95, **kw)
    ramp_off = off[1] + PAD >= RAMP_FROM
    assert ramp_off.sum() >= 100  # measured 172
    assert np.median(np.abs(off[2] - off[1] - SHIFT)[ramp_off]) > 3  # measured ~6
    ramp_on = on[1] + PAD >= RAMP_FROM
    assert not np.any(ramp_on)  # measured 0
    # the texture's matches are untouched
    for a, b in zip(on, off, strict=False):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b[~ramp_off])
    assert np.max(np.abs(on[2] - on[1] - SHIFT)) < 0.5  # measured 0.14
    assert on[4] == off[4]  # the same candidates tried


def test_dense_smooth_is_off_by_default_and_on_in_the_preset():
    assert OmniFlowConfig().matching.dense_smooth is None
    assert OmniFlowConfig.dense().matching.dense_smooth == DENSE["matching"]["dense_smooth"] < 1.0
    for bad in (1.5, 1.0):  # off is None, one spelling
        with pytest.raises(ValueError, match="dense_smooth"):
            OmniFlowConfig(matching={"dense_smooth": bad})
