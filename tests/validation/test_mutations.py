"""validation: the thresholds catch a biased, a timid and a misaligned method.

On the closed-form ``synthetic`` scene of ``validation/thresholds.toml`` (made
exactly as the end-to-end test makes it), the default omniflow variant's
checks must pass on its true output and FAIL on each of:

* its radial flow halved (``dh1_dt``, ``dh2_dt``, ``dr_dt`` x 0.5, the image
  flow re-formed from the polar components): caught by the radial gain band;
* zero flow (every flow column 0): caught by EPE and gain;
* the truth shifted by 0.3 px in x (a copy of the dataset whose
  ``gt.flow.dx`` is 0.3 px larger, ``gt.flow.dh`` and ``gt.flow.hdtheta``
  recomputed): caught by EPE.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from validation.calibrate import make_dataset
from validation.metrics import polar_components
from validation.report import write_report
from validation.runner import run_validation
from validation.thresholds import check_summary, load_thresholds

SCENE = "synthetic"


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    thresholds = load_thresholds()
    spec = thresholds["scenes"][SCENE]
    ds = make_dataset(spec, tmp_path_factory.mktemp("mut") / "ds", int(spec.get("seed", 0)))
    # Only the default variant runs here: keep its checks (and the baselines', which the
    # mutations do not touch).
    spec = dict(spec, check=[c for c in spec["check"] if c["method"] == "omniflow:default"])
    assert len(spec["check"]) >= 6
    return {"scenes": {SCENE: spec}}, ds, tmp_path_factory


def _checks(thresholds, ds, tmp, estimate=None):
    from omniflow.pipeline import estimate as real

    res = run_validation(ds, variants="default", baselines=[], progress=False,
                         estimate=estimate or real)  # fmt: skip
    summary = write_report(res, tmp.mktemp("r"))
    return check_summary(summary, thresholds, SCENE)


def _mutated(change):
    from omniflow.pipeline import estimate as real

    def estimate(frames1, frames2, rig, config, **kw):
        res = real(frames1, frames2, rig, config, **kw)
        res.columns = change(dict(res.columns), rig)
        return res

    return estimate


def _image_flow(c, rig):
    """Re-form dx, dy (cam1) and dx2, dy2 (cam2) from the polar columns."""
    cams = ((rig.cam1, "x", "y", "h1", "dh1_dt", "dx", "dy"),
            (rig.cam2, "x2", "y2", "h2", "dh2_dt", "dx2", "dy2"))  # fmt: skip
    for unit, x, y, h, dh, dx, dy in cams:
        _, theta = unit.polar_of_pixel(c[x], c[y])
        x1, y1 = unit.pixel_of_polar(c[h] + c[dh], theta + c["dtheta_dt"])
        c[dx], c[dy] = x1 - c[x], y1 - c[y]
    return c


def _half_radial(c, rig):
    for k in ("dh1_dt", "dh2_dt", "dr_dt"):
        c[k] = 0.5 * np.asarray(c[k])
    return _image_flow(c, rig)


def _zero(c, rig):
    for k in ("dh1_dt", "dh2_dt", "dtheta_dt", "dr_dt", "dx", "dy", "dx2", "dy2"):
        c[k] = np.zeros_like(np.asarray(c[k], dtype=np.float64))
    return c


def test_true_output_passes(setup):
    thresholds, ds, tmp = setup
    checks = _checks(thresholds, ds, tmp)
    assert all(c.passed for c in checks), [c.line() for c in checks if not c.passed]


@pytest.mark.parametrize(
    "change, caught_by",
    [(_half_radial, "radial.gain"), (_zero, "epe")],
    ids=["radial-halved", "zero-flow"],
)
def test_biased_or_timid_output_fails(setup, change, caught_by):
    thresholds, ds, tmp = setup
    failed = [c for c in _checks(thresholds, ds, tmp, _mutated(change)) if not c.passed]
    assert any(caught_by in c.metric for c in failed), [c.line() for c in failed]


def test_truth_shifted_by_a_third_of_a_pixel_fails(setup):
    from omnisim.dataset import open_dataset, read_exr, write_exr

    thresholds, ds, tmp = setup
    shifted = tmp.mktemp("shift") / "ds"
    shutil.copytree(ds, shifted)
    d = open_dataset(shifted)
    for k in range(d.frame_count):
        for cam, unit in (("cam1", d.rig.cam1), ("cam2", d.rig.cam2)):
            path = shifted / "frames" / f"{k:06d}" / f"{cam}.exr"
            ch = read_exr(path)
            xx, yy = unit.pixel_centres()
            ch["gt.flow.dx"] = ch["gt.flow.dx"] + np.float32(0.3)
            dh, hdth = polar_components(xx, yy, ch["gt.flow.dx"], ch["gt.flow.dy"],
                                        unit.x_c, unit.y_c)  # fmt: skip
            ch["gt.flow.dh"], ch["gt.flow.hdtheta"] = dh.astype(np.float32), hdth.astype(np.float32)
            write_exr(path, ch)
    failed = [c for c in _checks(thresholds, shifted, tmp) if not c.passed]
    assert any("epe" in c.metric for c in failed), [c.line() for c in failed]
