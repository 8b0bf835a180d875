"""validation.scorecard: the figures it prints, computed by hand from a small summary."""

from __future__ import annotations

import json
import math

import pytest

from omniflow.config import OmniFlowConfig
from validation.scorecard import main, mover_error, rows, table


def _comp(mean_est: float, mean_true: float, gain: float = 1.0, rms: float = 0.3) -> dict:
    return {"mean_est": mean_est, "mean_true": mean_true, "gain": gain, "true_rms": rms}


def _flow(epe_mean: float, epe_median: float, radial: dict, tangential: dict) -> dict:
    return {
        "all": {"epe": {"mean": epe_mean, "median": epe_median}, "radial": radial,
                "tangential": tangential},
        "density": {"points_per_frame": 900.0, "of_valid_pixels": 0.0045},
        "objects": {"box": {"n": 30, "radial": _comp(0.5, 0.4), "tangential": _comp(0.4, 0.3)},
                    "wall": {"n": 800, "radial": _comp(0.0, 0.0), "tangential": _comp(0, 0)}},
    }  # fmt: skip


def _method(config: OmniFlowConfig, default: bool) -> dict:
    return {
        "name": "omniflow[robust]" if default else "omniflow[robust;x]",
        "kind": "omniflow", "points": "own", "default": default, "config": config.to_dict(),
        "flow": {"cam1": _flow(0.02, 0.01, _comp(0.1, 0.1, 0.95), _comp(0.0, 0.0, 0.7, 0.01)),
                 "cam2": _flow(0.04, 0.03, _comp(0.2, 0.2, 0.99), _comp(0.1, 0.1, 1.01))},
        "baselines_at_same_points": {"DIS-medium": {"cam1": {"mean": 0.08, "median": 0.05},
                                                    "cam2": {"mean": 0.05, "median": 0.06}}},
        "stereo": {"all": {"outliers": 0.006}},
        "derived": {"ttc_relative_error": {"median": 0.023, "failure_share": 0.0}},
    }  # fmt: skip


@pytest.fixture
def summary() -> dict:
    return {
        "dataset": {"scene": "toy", "objects": {"1": "wall", "2": "box"}, "moving_objects": [2]},
        "methods": [
            _method(OmniFlowConfig(), True),
            _method(OmniFlowConfig.dense(dense_percentile=75.0), False),
            {"name": "DIS-medium", "kind": "baseline", "points": "dense"},
        ],
    }


def test_mover_error_is_the_mean_vectors_relative_distance():
    # est (0.5, 0.4), true (0.4, 0.3): |(0.1, 0.1)| / |(0.4, 0.3)| = 0.14142 / 0.5 = 0.28284.
    # Mutation (the tangential component left out, 0.1 / 0.4 = 0.25, or |est| / |true| - 1
    # = 0.28062) misses by more than 1e-3.
    block = {"radial": _comp(0.5, 0.4), "tangential": _comp(0.4, 0.3)}
    assert mover_error(block) == pytest.approx(math.sqrt(0.02) / 0.5, abs=1e-12)
    assert math.isnan(mover_error({"radial": _comp(0.1, 0.0), "tangential": _comp(0.1, 0.0)}))
    assert math.isnan(mover_error({}))  # an object with no point has no block


def test_rows_ratios_gains_labels_and_movers(summary):
    got = rows(summary)
    assert [r["row"] for r in got] == ["default", "dense,dense_percentile=75.0"]
    r = got[0]
    # EPE over DIS-medium's at the same points: 0.02 / 0.08, 0.01 / 0.05, 0.04 / 0.05, 0.03 / 0.06.
    assert r["cam1_x_mean"] == pytest.approx(0.25) and r["cam1_x_median"] == pytest.approx(0.2)
    assert r["cam2_x_mean"] == pytest.approx(0.8) and r["cam2_x_median"] == pytest.approx(0.5)
    # cam1's tangential truth has rms 0.01 px (< MIN_TRUE_RMS): its gain is not judged.
    assert (r["cam1_radial_gain"], r["cam1_tangential_gain"]) == ("0.95", "-")
    assert r["movers"] == [("box", 30, pytest.approx(0.28284, abs=1e-5),
                            pytest.approx(0.28284, abs=1e-5))]  # fmt: skip
    assert rows(summary, only=["default"]) == got[:1]
    text = table(got)
    assert "0.020 / 0.040 (0.25x / 0.80x)" in text and "box 30, 28.3 / 28.3" in text
    assert "0.6 %" in text and "0.023 / 0 %" in text


def test_cli_prints_the_table_and_names_a_bad_report(tmp_path, capsys, summary):
    (tmp_path / "ok").mkdir()
    (tmp_path / "ok" / "summary.json").write_text(json.dumps(summary))
    assert main([str(tmp_path / "ok")]) == 0
    assert "| toy | default | 900 (0.45 %) |" in capsys.readouterr().out
    assert main([str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing/summary.json" in err and "summary.json" in err
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "summary.json").write_text("{not json")
    assert main([str(tmp_path / "bad")]) == 2
    assert "not JSON" in capsys.readouterr().err
