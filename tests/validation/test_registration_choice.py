"""``--registration``: what omniflow is told about a rig with errors (recorded, none, card).

The truth-answering stand-in records the rig each call is given: recorded is the
dataset's rig with its errors, none the same rig without them (eq. 1), card the rig
file's. Rows stay distinct and summary.json says which each used; bad values are one
line with exit status 2.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from omniflow.cli.calibrate import rig_toml
from omniflow.config import OmniFlowConfig
from omniflow.geometry.rig import load_rig
from validation.oracle import OracleConfig, TruthOracle
from validation.report import write_report
from validation.runner import run_validation
from validation.synthdata import demo_scene, write_synthetic_dataset
from validation.variants import Registered, TrueMatches, with_registration

TRUE_ERRORS = {"cam1": {"cone_angle": 90.1, "mirror_tilt": [0.1, 0.0]}}
CARD_ERRORS = {"cam1": {"cone_angle": 90.05}, "cam2": {"mirror_tilt": [0.0, 0.02]}}


@pytest.fixture(scope="module")
def misaligned(tmp_path_factory) -> Path:
    """A 64 px closed-form dataset whose dataset.json records cam1's errors, and a rig
    file (as omniflow calibrate writes it) with other errors."""
    d = tmp_path_factory.mktemp("reg") / "ds"
    write_synthetic_dataset(d, demo_scene(64), 2, name="synthetic-demo", supersample=1)
    meta = json.loads((d / "dataset.json").read_text())
    meta["rig"]["errors"] = TRUE_ERRORS
    (d / "dataset.json").write_text(json.dumps(meta))
    card = dict(meta, rig={**meta["rig"], "errors": CARD_ERRORS})
    (d.parent / "card.json").write_text(json.dumps(card))
    (d.parent / "rig.toml").write_text(rig_toml(load_rig(d.parent / "card.json")))
    return d


def test_each_choice_is_the_rig_omniflow_is_given(misaligned, tmp_path):
    card = misaligned.parent / "rig.toml"
    rows = with_registration([("omniflow:default", OmniFlowConfig())], f"recorded,none,{card}")
    assert [n for n, _ in rows] == ["omniflow:default", "omniflow:default+registration=none",
                                    "omniflow:default+registration=card"]  # fmt: skip
    oracle, calls = TruthOracle(misaligned), []

    def estimate(f1, f2, rig, cfg, *, t=0):
        assert isinstance(cfg, OmniFlowConfig)  # the row's own config, unwrapped
        calls.append(rig)
        return oracle(f1, f2, rig, OracleConfig(), t=t)

    res = run_validation(misaligned, variants=rows, estimate=estimate, baselines=[],
                         progress=False)  # fmt: skip
    assert len(calls) == 6  # one pair: a warm-up and a timed call per row
    assert all(calls[i] is calls[i + 1] for i in (0, 2, 4))
    recorded, none, by_card = calls[0], calls[2], calls[4]
    assert recorded.cam1.errors.cone_angle == 90.1 and recorded.cam2.errors is None
    assert none.cam1.errors is None and none.cam2.errors is None
    assert (none.cam1.v, none.cam1.x_c, none.s) == (recorded.cam1.v, recorded.cam1.x_c,
                                                     recorded.s)  # fmt: skip
    assert by_card.cam1.errors.cone_angle == 90.05
    assert by_card.cam2.errors.mirror_tilt == pytest.approx((0.0, 0.02))
    summary = write_report(res, tmp_path / "r")
    reg = {m["name"]: m["config"].get("registration") for m in summary["methods"]
           if m["kind"] == "omniflow"}  # fmt: skip
    assert reg == {"omniflow:default": "recorded", "omniflow:default+registration=none": "none",
                   "omniflow:default+registration=card": "card"}  # fmt: skip
    rig_file = next(m["config"]["registration_rig"] for m in summary["methods"]
                    if m["name"].endswith("=card"))  # fmt: skip
    assert rig_file == str(card.resolve())
    assert {r["method"] for r in res.rows} >= set(reg)  # frames.csv rows stay distinct


def test_rows_without_matching_are_kept_once():
    cfg = OmniFlowConfig()
    rows = with_registration([("a", cfg), ("t", TrueMatches(cfg))], "none")
    assert [n for n, _ in rows] == ["a+registration=none", "t"]
    assert isinstance(rows[0][1], Registered) and rows[0][1].registration == "none"
    assert with_registration(rows, None) is rows


def test_bad_registration_is_one_line_exit_2(misaligned, tmp_path, capsys):
    from validation.cli import main as omnivalidate

    wrong = misaligned.parent / "wrong.toml"  # a card calibrated at another resolution
    meta = json.loads((misaligned / "dataset.json").read_text())
    for cam in meta["cameras"]:
        cam.update(width=128, height=128, x_c=64.0, y_c=64.0, r_m=60.0, v=180.0)
    (misaligned.parent / "wrong.json").write_text(json.dumps(meta))
    wrong.write_text(rig_toml(load_rig(misaligned.parent / "wrong.json")))
    cases = [("bogus", "--registration 'bogus': no such rig file; expected recorded, none"),
             ("none,none", "each of recorded, none, card at most once"),
             ("none,x", "--registration 'x': no such rig file"),
             (str(wrong), "cam1 is 128 x 128 px, the dataset's 64 x 64")]  # fmt: skip
    for value, fragment in cases:
        rc = omnivalidate([str(misaligned), "--out", str(tmp_path / "o"), "--variants",
                           "default", "--baselines", "none", "--no-progress",
                           "--registration", value])  # fmt: skip
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert rc == 2, (value, err)
        assert len(err) == 1 and fragment in err[0], err
