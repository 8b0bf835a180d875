"""omniflow.matching.dense_kernels.ncc_offsets (the densification's search) against the robust
rule's
profiles (omniflow.matching.robust.Descriptors): the same normalised cross-correlation.

Random float32 tables (n_theta 40, 120 columns), profiles of 2 w + 1 = 9 samples every
2 columns on one line: measured largest difference 1.1e-6; Descriptors sums in float32 by
box filters, the kernel in float64.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.matching.dense_kernels import ncc_offsets
from omniflow.matching.robust import Descriptors


def _case(seed: int = 0):
    rng = np.random.default_rng(seed)
    t1 = rng.random((40, 120)).astype(np.float32)
    t2 = rng.random((40, 120)).astype(np.float32)
    w, stride = 4, 2
    n = 300
    k = rng.integers(0, 40, n)
    j = rng.integers(w * stride, 120 - w * stride, n)
    cols = np.clip(j[:, None] + rng.integers(-3, 4, (n, 5)), w * stride, 119 - w * stride)
    return t1, t2, k, j, cols, w, stride


def _reference(t1, t2, k, j, cols, w, stride):
    d1 = Descriptors(t1, w, stride)(k, j)
    d2 = Descriptors(t2, w, stride)(np.broadcast_to(k[:, None], cols.shape), cols)
    return np.einsum("nl,nsl->ns", d1, d2)


def _kernel(t1, t2, k, j, cols, w, stride):
    out = np.empty(cols.shape)
    ncc_offsets(t1, t2, k.astype(np.int64), j.astype(np.int64), cols.astype(np.int64),
                w, stride, out)  # fmt: skip
    return out


def test_ncc_offsets_equals_the_descriptors_ncc():
    t1, t2, k, j, cols, w, stride = _case()
    ref = _reference(t1, t2, k, j, cols, w, stride)
    got = _kernel(t1, t2, k, j, cols, w, stride)
    assert np.max(np.abs(got - ref)) < 1e-4  # measured 1.1e-6
    # a profile against itself scores 1
    same = _kernel(t1, t1, k, j, j[:, None], w, stride)
    np.testing.assert_allclose(same, 1.0, atol=1e-9)  # measured 2.2e-15


def test_ncc_check_catches_a_profile_off_by_one_line():
    """Mutation: the kernel reading the neighbouring line of table 2 (k + 1): the check
    fails (measured largest difference 1.48)."""
    t1, t2, k, j, cols, w, stride = _case()
    ref = _reference(t1, t2, k, j, cols, w, stride)
    got = _kernel(t1, np.roll(t2, -1, axis=0), k, j, cols, w, stride)
    assert np.max(np.abs(got - ref)) > 1e-4


@pytest.mark.parametrize("n_cols", [7, 5, 1, 9])
def test_densifys_kernel_equals_ncc_offsets_bit_for_bit(n_cols):
    """omniflow.matching.dense.ncc_offsets (four columns' sums at once) against
    omniflow.matching.dense_kernels.ncc_offsets: every value equal, for column counts that fill the
    groups of four or leave one to three over. Mutation caught: a group's last
    column written from the wrong accumulator (any n_cols not a multiple of 4)."""
    from omniflow.matching.dense import ncc_offsets as grouped

    t1, t2, k, j, _, w, stride = _case(seed=2)
    rng = np.random.default_rng(3)
    cols = np.clip(j[:, None] + rng.integers(-3, 4, (j.size, n_cols)), w * stride,
                   119 - w * stride)  # fmt: skip
    out = np.empty(cols.shape)
    grouped(t1, t2, k.astype(np.int64), j.astype(np.int64), cols.astype(np.int64),
            w, stride, out)  # fmt: skip
    np.testing.assert_array_equal(out, _kernel(t1, t2, k, j, cols, w, stride))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_candidates_equal_the_numpy_form(seed):
    """omniflow.matching.dense.candidates (a walk along each line) against
    candidates_numpy (dilation, then searchsorted): the same samples, in the same
    order, with the same disparity guesses, on random derivative tables with seeds
    close together (interpolated guesses), far apart, at the core's ends, and pairs
    that disagree by more than a column (no candidate between them). Mutation caught:
    interpolating across a depth edge."""
    from omniflow.matching.dense import candidates, candidates_numpy

    rng = np.random.default_rng(seed)
    n_lines, n_cols, pad, n_h, reach = 30, 140, 10, 120, 8
    fh1 = rng.standard_normal((n_lines, n_cols)).astype(np.float32)
    m = 150
    k = rng.integers(0, n_lines, m)
    jj = rng.integers(pad, pad + n_h, m)
    pairs = np.unique(k * n_cols + jj)  # seeds are unique samples
    k, jj = pairs // n_cols, pairs % n_cols
    disp = rng.normal(30.0, 1.5, k.size)
    out = candidates(fh1, 0.5, pad, n_h, k, jj, disp, reach)
    ref = candidates_numpy(fh1, 0.5, pad, n_h, k, jj, disp, reach)
    assert out[0].size > 100
    for a, b in zip(out, ref, strict=True):
        np.testing.assert_array_equal(a, b)
