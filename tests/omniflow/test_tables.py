"""omniflow.matching.tables: abs_percentile and radial_derivative against their numpy
forms, value for value."""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.matching.tables import abs_percentile, radial_derivative


@pytest.mark.parametrize("q", [80.0, 60.0, 50.0, 33.3, 99.9, 0.0, 12.5, 100.0, 80])
def test_abs_percentile_is_numpys(q):
    """Random float32 tables of many sizes and scales, some with ties (quarters) and
    some all zero, non-contiguous views too: the same float as
    np.percentile(np.abs(a), q) every time. Mutations caught: taking the lower order
    statistic only, or interpolating in float64 (each changes some of these values)."""
    rng = np.random.default_rng(int(q * 10))
    for trial in range(150):
        shape = (int(rng.integers(1, 60)), int(rng.integers(2, 80)))
        a = (rng.standard_normal(shape) * 10.0 ** rng.integers(-6, 3)).astype(np.float32)
        if trial % 3 == 0:
            a = (np.round(a * 4) / 4).astype(np.float32)
        if trial % 11 == 0:
            a[:] = 0
        if trial % 5 == 0:
            a = a[::2, 1:]
            if a.size < 2:
                continue
        assert abs_percentile(a, q) == float(np.percentile(np.abs(a), q)), (trial, a.shape)


def test_abs_percentile_hands_nan_and_other_inputs_to_numpy():
    a = np.ones((4, 5), np.float32)
    a[1, 2] = np.nan
    assert np.isnan(abs_percentile(a, 80.0))
    b = np.arange(20.0).reshape(4, 5)  # float64: numpy's own
    assert abs_percentile(b, 80.0) == float(np.percentile(b, 80.0))
    assert abs_percentile(b.astype(np.float32), np.float64(80.0)) == float(
        np.percentile(b.astype(np.float32), np.float64(80.0))
    )


@pytest.mark.parametrize("step", [1.0, 1.3, 1.0471975511965976])
def test_radial_derivative_is_the_numpy_central_difference(step):
    """The compiled float32 path against numpy's (subtract, then scale by the Python
    float 0.5 / step: float32 ops), end columns copied: every value equal; a float64
    table takes numpy's path. Mutation caught: scaling in float64 (values move)."""
    rng = np.random.default_rng(int(step * 100))
    t = (rng.standard_normal((37, 90)) * 10.0 ** rng.integers(-3, 2)).astype(np.float32)
    ref = np.empty_like(t)
    np.subtract(t[:, 2:], t[:, :-2], out=ref[:, 1:-1])
    ref[:, 1:-1] *= 0.5 / step
    ref[:, 0], ref[:, -1] = ref[:, 1], ref[:, -2]
    out = radial_derivative(t, step)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, ref)
    t64 = t.astype(np.float64)
    inner = (t64[:, 2:] - t64[:, :-2]) * (0.5 / step)
    np.testing.assert_array_equal(radial_derivative(t64, step)[:, 1:-1], inner)


def test_equal_radii_give_equal_map_columns():
    """The short pass reads the long pass's table columns where polar_radii are equal
    (radial._sampled_columns): the premise, that polar_maps' columns are then equal
    value for value, for cam1 (h0, step) and cam2 (both scaled), on the default rig."""
    from omniflow.geometry.rig import Rig
    from omniflow.matching.tables import polar_maps, polar_radii

    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=512)
    scale2 = rig.cam2.v / rig.cam1.v
    for unit, s in ((rig.cam1, 1.0), (rig.cam2, scale2)):
        wide = polar_maps(unit, 360, s * (16.0 - 34), s * 1.0, 235 + 68)
        narrow = polar_maps(unit, 360, s * (16.0 - 18), s * 1.0, 235 + 36)
        same = np.array_equal(
            polar_radii(s * (16.0 - 34), s * 1.0, 303)[16 : 16 + 271],
            polar_radii(s * (16.0 - 18), s * 1.0, 271),
        )
        assert same == all(
            np.array_equal(a[:, 16 : 16 + 271], b) for a, b in zip(wide, narrow, strict=True)
        )
        assert same or s != 1.0  # cam1's radii are whole numbers: always equal
