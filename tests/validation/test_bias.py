"""validation: bias (gain), zero flow, time to contact with failures, objects and density.

Each figure is checked on hand values and on the truth oracle, where the
answers are known exactly (gain 1 for the truth, 0 for zero flow).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from validation.metrics import gain
from validation.oracle import OracleConfig, TruthOracle
from validation.report import write_report
from validation.runner import run_validation, ttc_scores
from validation.summary import find_method
from validation.synthdata import demo_scene, write_synthetic_dataset


def test_gain_hand_values():
    true = np.array([-1.0, 0.5, 1.0, 2.0])
    g = gain(0.5 * true, true)
    assert g["gain"] == pytest.approx(0.5) and g["slope"] == pytest.approx(0.5)
    assert g["intercept"] == pytest.approx(0.0, abs=1e-12)
    assert g["mean_signed"] == pytest.approx(-0.5 * true.mean())
    # A constant offset: the straight line finds it, the gain through the origin mixes it in.
    g = gain(true + 0.3, true)
    assert g["slope"] == pytest.approx(1.0) and g["intercept"] == pytest.approx(0.3)
    assert g["mean_signed"] == pytest.approx(0.3) and g["median_signed"] == pytest.approx(0.3)
    assert g["gain"] == pytest.approx(1.0 + 0.3 * true.sum() / (true**2).sum())
    g = gain(np.zeros(4), true)
    assert g["gain"] == 0.0 and g["slope"] == 0.0
    # Non-finite pairs are left out; no truth spread: no slope, no warning.
    g = gain([1.0, np.nan, 2.0], [1.0, 1.0, np.inf])
    assert g["n"] == 1 and math.isnan(g["slope"]) and g["gain"] == 1.0
    assert gain([], [])["n"] == 0
    # No motion in that direction (rms below 0.01 px): no gain, not 1e12.
    g = gain([0.01, -0.02, 0.03], [1e-9, -2e-9, 1e-9])
    assert math.isnan(g["gain"]) and math.isnan(g["slope"]) and g["mean_signed"] > 0


def test_ttc_failures_count_as_infinite_error():
    true = np.array([10.0, 10.0, 10.0, 10.0])
    est = np.array([11.0, 9.0, np.inf, -5.0])  # two estimated right, one receding, one negative
    s = ttc_scores(est, true)
    assert s["n"] == 4 and s["failures"] == 2 and s["failure_share"] == 0.5
    assert s["median_of_successes"] == pytest.approx(0.1)
    assert math.isinf(s["median"])  # half the points failed: the median is infinite
    s = ttc_scores(np.array([11.0, 9.0, 10.0]), true[:3])
    assert s["failures"] == 0 and s["median"] == pytest.approx(0.1)


@pytest.fixture(scope="module")
def oracle_summary(tmp_path_factory):
    d = tmp_path_factory.mktemp("synth") / "ds"
    write_synthetic_dataset(d, demo_scene(64), 3, name="synthetic-demo", supersample=1)
    res = run_validation(
        d,
        variants=[("truth-oracle", OracleConfig())],
        estimate=TruthOracle(d),
        baselines=["zero-flow"],
        progress=False,
    )
    return res, write_report(res, tmp_path_factory.mktemp("r"))


def test_truth_has_gain_one_and_zero_flow_gain_zero(oracle_summary):
    _, summary = oracle_summary
    oracle = find_method(summary, "truth-oracle")["flow"]["cam1"]["all"]
    zero = find_method(summary, "zero-flow", "omniflow points")["flow"]["cam1"]["all"]
    for comp in ("radial", "tangential"):
        assert oracle[comp]["gain"] == pytest.approx(1.0, abs=1e-9)
        assert oracle[comp]["slope"] == pytest.approx(1.0, abs=1e-9)
        assert zero[comp]["gain"] == 0.0
    assert zero["epe"]["median"] > 0.05  # the demo moves: zero flow is wrong
    # The perfect method is clearly below zero flow: no warning about it in the headline.
    assert not [line for line in summary["headline"] if line.startswith("WARNING truth-oracle")]
    assert summary["headline"][0].startswith("cam1, truth-oracle: unbiased")


def test_bias_verdict_needs_true_motion():
    from validation.summary import _biased

    def block(gain, rms):
        g = {"gain": gain, "true_rms": rms}
        return {"all": {"radial": g, "tangential": {"gain": 1.0, "true_rms": rms}}}

    assert _biased(block(0.6, 0.3)) == "biased (radial gain 0.60)"
    assert _biased(block(0.9, 0.3)) == "biased (radial gain 0.90)"  # outside 1 +- 0.05
    assert _biased(block(0.97, 0.3)) == "unbiased"
    # A static scene: the truth barely moves, the gain is noise over nothing.
    assert _biased(block(-0.02, 0.01)).startswith("bias not judged")


def test_a_row_with_no_points_is_not_compared(tmp_path, monkeypatch):
    """Zero matches (a dark or constant frame) is an answer: the headline says no points
    and 'not comparable', not 'NOT clearly below zero flow' nor a bias verdict about a
    truth rms that was never measured; the empty figures say why they are empty."""
    import matplotlib.text

    import validation.report_figures as figures

    texts: dict[str, list[str]] = {}
    real_save = figures.save

    def save(fig, path):
        texts[Path(path).name] = [t.get_text() for t in fig.findobj(matplotlib.text.Text)]
        real_save(fig, path)

    monkeypatch.setattr(figures, "save", save)
    d = tmp_path / "ds"
    write_synthetic_dataset(d, demo_scene(64), 2, name="synthetic-demo", supersample=1)
    oracle = TruthOracle(d)

    def no_points(*args, **kwargs):
        res = oracle(*args, **kwargs)
        res.columns = {k: v[:0] for k, v in res.columns.items()}
        return res

    res = run_validation(d, variants=[("none", OracleConfig())], estimate=no_points,
                         baselines=["zero-flow"], progress=False)  # fmt: skip
    head = write_report(res, tmp_path / "r")["headline"]
    assert head[0].startswith("cam1, none: no points scored -- 0 points"), head[0]
    zero = [line for line in head if line.startswith("cam1, omniflow vs zero-flow")]
    assert zero and zero[0].split(" -- ")[0].endswith(": not comparable"), zero
    assert "no row has a median EPE to plot: no points were scored" in texts["accuracy_vs_time.png"]
    assert "no points on this frame" in texts["error_maps.png"]
    for name in ("error_vs_range.png", "error_vs_speed.png"):
        assert "no points to bin: the rows scored none" in texts[name], name


def test_density_and_objects_with_no_points(oracle_summary):
    res, summary = oracle_summary
    f = find_method(summary, "truth-oracle")["flow"]["cam1"]
    d = f["density"]
    # The oracle answers at every 3rd pixel the other camera sees (OracleConfig.step = 3),
    # less the few without bilinear truth: about a third of the stereo pixels.
    assert 0.25 < d["of_stereo_pixels"] <= 1 / 3 + 1e-9
    assert d["of_valid_pixels"] < d["of_stereo_pixels"]
    assert d["points_per_frame"] == pytest.approx(f["all"]["n"] / 2)
    # Every object of the dataset is listed, with n and its pixel share.
    names = set(res.dataset["objects"].values())
    assert names <= set(f["objects"])
    dense_zero = find_method(summary, "zero-flow", "dense")["flow"]["cam1"]["objects"]
    for name in names:
        assert dense_zero[name]["n"] == dense_zero[name]["valid_pixels"]


def test_an_object_never_scored_shows_zero(tmp_path):
    d = tmp_path / "ds"
    write_synthetic_dataset(d, demo_scene(64), 3, name="synthetic-demo", supersample=1)
    oracle = TruthOracle(d)

    def skip_object_1(*args, **kwargs):
        res = oracle(*args, **kwargs)
        from validation.sampling import sample_truth

        g1 = oracle.ds.read_frame(oracle.pairs[(oracle.calls - 1) % len(oracle.pairs)], "cam1")
        ids = sample_truth(g1, res.columns["x"], res.columns["y"])["gt.object"]
        keep = np.rint(ids) != 1
        res.columns = {k: v[keep] for k, v in res.columns.items()}
        return res

    res = run_validation(d, variants=[("o", OracleConfig())], estimate=skip_object_1,
                         baselines=[], progress=False)  # fmt: skip
    summary = write_report(res, tmp_path / "r")
    name = res.dataset["objects"]["1"]
    block = find_method(summary, "o")["flow"]["cam1"]["objects"][name]
    assert block["n"] == 0 and block["valid_pixels"] > 0 and block["density"] == 0.0
    md = (tmp_path / "r" / "report.md").read_text()
    objects_table = md.split("## Objects")[1].split("\n## ")[0]
    assert name in objects_table


def test_gain_se_matches_the_gains_scatter_over_noise_draws():
    """gain_se against the spread of the gain over 400 noise draws at the same truth
    (400 points, gain 0.9, noise 0.1 px, constant or growing with the truth): measured
    0.95 of the spread either way (HC0; the spread itself is known to +-3.5 % from 400
    draws), so the bound is 0.85-1.15. Residuals taken about 1 instead of the gain read
    1.2x here; the standard error of a mean (over sqrt(sum true**2)) 11x."""
    true = np.random.default_rng(0).uniform(-1.0, 1.0, 400)
    for scale in (np.ones_like(true), 0.2 + np.abs(true)):
        gains, ses = [], []
        for seed in range(400):
            noise = np.random.default_rng(100 + seed).normal(0.0, 0.1, true.size) * scale
            g = gain(0.9 * true + noise, true)
            gains.append(g["gain"])
            ses.append(g["gain_se"])
        assert 0.85 < np.mean(ses) / np.std(gains) < 1.15  # measured 0.952, 0.957
    assert math.isnan(gain([0.01, -0.02, 0.03], [1e-9, -2e-9, 1e-9])["gain_se"])


def test_gain_se_flags_a_gain_set_by_a_few_points():
    """low_texture's mechanism (docs/decisions/matching.md): 391
    points on the line with true radial flow of rms 0.068 px, and the nine wrong matches'
    estimated flows at their true 0.18-0.22 px as measured in pair 0. The nine take the
    gain from 1.00 to 0.65 and its standard error from 0.004 to 0.33 (measured), so the
    gain is 0.65 +- 0.33: set by nine points, not a shrink of the others."""
    rng = np.random.default_rng(1)
    true = rng.normal(0.0, 0.068, 391)
    est = true + rng.normal(0.0, 0.005, true.size)
    bad_est = [-1.899, -1.104, -1.090, 1.347, -0.669, 0.815, 0.672, -0.240, 0.257]
    bad_true = [0.182, 0.195, 0.191, 0.219, 0.199, 0.215, 0.207, 0.200, 0.208]
    clean = gain(est, true)
    both = gain(np.r_[est, bad_est], np.r_[true, bad_true])
    assert clean["gain"] == pytest.approx(1.0, abs=0.01)  # measured 0.995
    assert clean["gain_se"] < 0.01  # measured 0.0042
    assert both["gain"] < 0.8  # measured 0.649
    assert both["gain_se"] > 0.2  # measured 0.328
    assert abs(both["gain"] - 1.0) < 2.0 * both["gain_se"]
