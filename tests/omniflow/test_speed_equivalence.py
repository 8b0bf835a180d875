"""The sped-up matcher changes no output column: estimate() against a stored reference.

The reference (tests/data/speed_reference.npz) holds every column of
:func:`omniflow.pipeline.estimate` on the closed-form frames of :func:`cases`,
computed by main's code without the speed work of issue 10 (main at 902d84e, the
edges-only defaults; earlier made from 77434fb, 1769dfa and ed286b6, the last with the
densification on by default, where the same kind of figures held), from a clean
checkout of it::

    git worktree add --detach /tmp/speed_ref 902d84e
    PYTHONPATH=/tmp/speed_ref python tests/omniflow/test_speed_equivalence.py --write

(run from this repository's root; the script imports omniflow and the test
helpers from /tmp/speed_ref, so the figures are that commit's). The cases
cover the default matcher (long and short pass, left-right check, alias
test) and a thin textured pole in front of the wall (the short pass's job). (A third
case, with the self-similarity test and multi-line patches, went with those knobs:
docs/decisions/retired_knobs.md.)
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from omniflow.config import OmniFlowConfig
from omniflow.geometry.rig import Rig
from omniflow.pipeline import estimate
from omnisim.synthetic import Cylinder, Motion, SyntheticScene, Texture

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "speed_reference.npz"
SIZE = 512

# Largest |new - reference| over a column, relative to the column's largest |value|.
# The compiled matcher (omniflow.matching.ncc) sums each NCC in double where main used
# a float32 BLAS product, so an NCC moves by a float32 ulp or two and the sub-pixel
# parabola through three of them amplifies that into h2 (1.4e-4 px at most on the
# rendered scenes). Measured with this file's cases against main 902d84e: 3.4e-5
# (confidence, room_pole); against ed286b6 (densified) 1.6e-5 (f2_theta); on the 12
# pairs of /work/data/{default,approach,crossing,independent_movers} (103,579 points
# against ed286b6, 9,959 against 1769dfa, the same points): 3.5e-5 and 4.2e-5 (D).
# Every matched sample (theta, h1) must be identical.
RELATIVE_TOL = 5e-5


def _scene(pole: bool) -> SyntheticScene:
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=SIZE)
    bodies = ()
    if pole:
        bodies = (
            Cylinder(
                radius=0.04, centre=(0.9, 0.4), id=3, name="pole",
                motion=Motion(velocity=(-0.01, 0.004)),
                texture=Texture.random(11, wavelengths=(0.02, 0.2), contrast=0.6),
            ),
        )  # fmt: skip
    return SyntheticScene.room(
        rig, wall_radius=3.0, ceiling=2.5, texture_seed=3,
        robot=Motion(velocity=(0.004, 0.002), yaw_rate=0.002), bodies=bodies,
    )  # fmt: skip


def cases() -> dict[str, tuple[bool, OmniFlowConfig]]:
    return {
        "room": (False, OmniFlowConfig()),
        "room_pole": (True, OmniFlowConfig()),
    }


def compute(name: str) -> dict[str, np.ndarray]:
    pole, config = cases()[name]
    scene = _scene(pole)
    f1 = [scene.render("cam1", t).astype(np.float32) for t in range(2)]
    f2 = [scene.render("cam2", t).astype(np.float32) for t in range(2)]
    res = estimate(f1, f2, scene.rig, config, t=0)
    out = {k: np.asarray(res[k]) for k in res.columns}
    out["n_significant"] = np.asarray(res.n_significant)
    return out


def _order(cols: dict[str, np.ndarray]) -> np.ndarray:
    """Rows sorted by (theta, h1, h2): the comparison does not depend on the row order."""
    return np.lexsort((cols["h2"], cols["h1"], cols["theta"]))


@pytest.fixture(scope="module")
def reference():
    with np.load(REFERENCE) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("name", list(cases()))
def test_columns_match_reference(name, reference):
    ref = {k[len(name) + 1 :]: v for k, v in reference.items() if k.startswith(name + "/")}
    new = compute(name)
    assert int(new.pop("n_significant")) == int(ref.pop("n_significant"))
    assert sorted(new) == sorted(ref)
    assert new["theta"].size == ref["theta"].size > 100
    a, b = _order(new), _order(ref)
    # the matched samples themselves are the same (theta and h1 are on the table grid)
    np.testing.assert_array_equal(new["theta"][a], ref["theta"][b])
    np.testing.assert_array_equal(new["h1"][a], ref["h1"][b])
    for k in ref:
        x, y = new[k][a], ref[k][b]
        assert x.dtype == y.dtype, k
        if x.dtype.kind == "f":
            scale = float(np.nanmax(np.abs(y))) if np.any(np.isfinite(y)) else 0.0
            np.testing.assert_array_equal(np.isnan(x), np.isnan(y), err_msg=k)
            fin = np.isfinite(y)
            err = float(np.max(np.abs(x[fin] - y[fin]), initial=0.0))
            assert err <= RELATIVE_TOL * max(scale, 1e-300), (k, err, scale)
        else:
            np.testing.assert_array_equal(x, y, err_msg=k)


def _write() -> None:
    arrays = {}
    for name in cases():
        for k, v in compute(name).items():
            arrays[f"{name}/{k}"] = v
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    tmp = REFERENCE.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(REFERENCE)
    print(f"wrote {REFERENCE} ({len(arrays)} arrays)")


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        _write()
    else:
        sys.exit("usage: PYTHONPATH=<checkout of 77434fb> python " + __file__ + " --write")


@pytest.mark.parametrize("rig_name", ["paper", "asymmetric"])
def test_rim_fill_equals_whole_image_remap(rig_name):
    """fill_outside_rim remaps only the pixels beyond the rim: bit for bit main's whole-image
    remap (whose map is the identity inside, an exact copy there)."""
    import cv2

    from omniflow.fit.series import fill_outside_rim
    from tests.helpers.scenes import asymmetric_rig, paper_rig

    rig = paper_rig(256) if rig_name == "paper" else asymmetric_rig(256)
    rng = np.random.default_rng(5)
    for unit in (rig.cam1, rig.cam2):
        image = cv2.GaussianBlur(rng.random((256, 256)).astype(np.float32), (5, 5), 1.0)
        # main 77434fb's fill_outside_rim, verbatim: a map over the whole image
        x, y = unit.pixel_centres()
        h_i, theta = unit.polar_of_pixel(x, y)
        edge = unit.r_m - 1.0
        src = np.where(h_i > edge, np.maximum(2.0 * edge - h_i, 0.0), h_i)
        xs, ys = unit.pixel_of_polar(src, theta)
        mx, my = (xs - 0.5).astype(np.float32), (ys - 0.5).astype(np.float32)
        ref = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        out = fill_outside_rim(image, unit)
        assert np.count_nonzero(ref != image) > 1000  # the fill changed the corners
        np.testing.assert_array_equal(out, ref)


@pytest.mark.parametrize(("w", "stride"), [(16, 1), (16, 2), (8, 3)])
def test_kernel_profiles_equal_descriptors(w, stride):
    """The compiled profiles (the matcher's, and Descriptors') are main's whole-table
    Descriptors' (now TableDescriptors), bit for bit; so are indices off the table's
    profile range (Descriptors hands them to TableDescriptors)."""
    import cv2

    from omniflow.matching.ncc import _profile
    from omniflow.matching.robust import Descriptors, TableDescriptors

    rng = np.random.default_rng(1)
    table = (0.5 + 0.05 * rng.standard_normal((90, 200))).astype(np.float32)
    table = cv2.GaussianBlur(table, (1, 9), 0)
    k = rng.integers(0, 90, 3000)
    j = rng.integers(w * stride, 200 - w * stride, 3000)
    ref = TableDescriptors(table, w, stride)(k, j)
    out = np.empty_like(ref)
    for i in range(k.size):
        _profile(table, k[i], j[i], w, stride, out, i)
    np.testing.assert_array_equal(out, ref)
    desc = Descriptors(table, w, stride)
    np.testing.assert_array_equal(
        desc(k.reshape(50, 60), j.reshape(50, 60)), ref.reshape(50, 60, -1)
    )
    edge = np.array([0, w * stride - 1, 200 - w * stride])  # windows leaving the table
    np.testing.assert_array_equal(
        desc(k[:3], edge), TableDescriptors(table, w, stride)(k[:3], edge)
    )
