"""The harness's eq. (14) flag (validation.scoring_flags) against hand-computed values.

Closed-form truth: validation.synthdata.vertical_scene at 96 px (the robot still, a
pillar, id 3, rising 20 mm per frame; the room static), 2 frames. A stand-in method
answers the truth (validation.oracle.TruthOracle) at every second stereo pixel, flags
(``coupled`` = 0) every other pillar point and every 10th room point, and adds
FLAGGED_ERR px to the flagged points' dx in both cameras. So the flagged points'
EPE is exactly FLAGGED_ERR and the unflagged points' 0, and the flag's precision and
recall follow from counting the points: the pillar's points are the only ones that
break eq. (14) (the room's axial motion is exactly 0 and the pillar's violation,
s v dh / ((d + r)(s - h)), is several times BREAK_PX there: checked below).
"""

from __future__ import annotations

import numpy as np
import pytest

from validation.leaderboard import scene_rows
from validation.oracle import OracleConfig, TruthOracle
from validation.runner import run_validation
from validation.scoring_flags import BREAK_PX
from validation.summary import summarize
from validation.synthdata import vertical_scene, write_synthetic_dataset

FLAGGED_ERR = 0.3  # px added to a flagged point's dx
PILLAR = 3


class FlaggingOracle(TruthOracle):
    """The truth, with a ``coupled`` column set by a fixed rule and the flagged points
    moved FLAGGED_ERR px in x; it keeps what it flagged for the test to count."""

    def __init__(self, dataset_dir):
        super().__init__(dataset_dir)
        self.calls_made = []

    def __call__(self, frames1, frames2, rig, config, *, t=0):
        res = super().__call__(frames1, frames2, rig, config, t=t)
        cols = res.columns
        g1 = self.ds.read_frame(self.pairs[(self.calls - 1) % len(self.pairs)], "cam1")
        iy, ix = cols["y"].astype(int), cols["x"].astype(int)  # pixel centres
        on = g1["gt.object"][iy, ix] == PILLAR
        k = np.arange(on.size)
        flag = (on & (np.cumsum(on) % 2 == 0)) | (~on & (k % 10 == 0))
        cols["coupled"] = np.where(flag, 0.0, 1.0)
        cols["dx"] = cols["dx"] + FLAGGED_ERR * flag
        cols["dx2"] = cols["dx2"] + FLAGGED_ERR * flag
        self.calls_made.append((on, flag))
        return res


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    d = tmp_path_factory.mktemp("vertical")
    write_synthetic_dataset(d, vertical_scene(96, vz=0.02), 2, name="vertical", supersample=1)
    oracle = FlaggingOracle(d)
    res = run_validation(d, variants=[("oracle", OracleConfig(step=2))], baselines=[],
                         estimate=oracle, progress=False)  # fmt: skip
    return res, summarize(res), oracle


def test_the_pillar_alone_breaks_eq_14(scored):
    res, _, oracle = scored
    (rec,) = res.flags["oracle"]
    on, _ = oracle.calls_made[-1]
    assert rec["object"].size == on.size  # every oracle point has truth
    pillar = rec["object"] == PILLAR
    assert np.all(rec["violation"][~pillar] == 0.0)  # the static room
    assert np.abs(rec["violation"][pillar]).min() > 2 * BREAK_PX
    np.testing.assert_array_equal(rec["breaks"], pillar)


def test_flag_counts_precision_and_recall_by_hand(scored):
    _, summary, oracle = scored
    on, flag = oracle.calls_made[-1]
    n, nf, both = on.size, int(flag.sum()), int((on & flag).sum())
    assert on.sum() >= 20 and both >= 10 and nf - both >= 10  # enough of each to count
    fl = summary["methods"][0]["flags"]
    assert (fl["n_points"], fl["n_flagged"], fl["n_breaks"]) == (n, nf, int(on.sum()))
    assert fl["share_flagged"] == pytest.approx(nf / n)
    assert fl["precision"] == pytest.approx(both / nf)
    assert fl["recall"] == pytest.approx(both / on.sum())


def test_flagged_and_unflagged_points_are_scored_apart(scored):
    _, summary, oracle = scored
    _, flag = oracle.calls_made[-1]
    fl = summary["methods"][0]["flags"]
    for cam in ("cam1", "cam2"):
        un, fg = fl["flow"]["unflagged"][cam]["all"], fl["flow"]["flagged"][cam]["all"]
        assert un["n"] + fg["n"] == summary["methods"][0]["flow"][cam]["all"]["n"]
        assert un["epe"]["mean"] == pytest.approx(0.0, abs=1e-9)
        assert fg["epe"]["mean"] == pytest.approx(FLAGGED_ERR, abs=1e-9)
        assert fg["epe"]["median"] == pytest.approx(FLAGGED_ERR, abs=1e-9)
    assert fl["flow"]["flagged"]["cam1"]["all"]["n"] == flag.sum()
    row = scene_rows("vertical", "train", summary)[0]
    assert row["flagged"] == pytest.approx(flag.mean())
    assert row["unflagged_epe"] == pytest.approx(0.0, abs=1e-9)
    assert row["flagged_epe"] == pytest.approx(FLAGGED_ERR, abs=1e-9)
    assert any(line.startswith("eq. (14) flag, oracle") for line in summary["headline"])


def test_a_row_without_the_flag_gets_no_flag_block(tmp_path):
    d = tmp_path / "ds"
    write_synthetic_dataset(d, vertical_scene(64), 2, name="vertical", supersample=1)
    res = run_validation(d, variants=[("oracle", OracleConfig())], baselines=[],
                         estimate=TruthOracle(d), progress=False)  # fmt: skip
    m = summarize(res)["methods"][0]
    assert "flags" not in m
    assert np.isnan(scene_rows("vertical", "train", summarize(res))[0]["flagged"])
