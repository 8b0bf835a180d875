"""Row names of the omniflow variants (validation.variants.variant_name): short and stable.

A preset is named by the preset alone, whatever its fields are; another config by the
preset it differs from in the fewest fields and those fields; the rows of the flow step
on the true matches add ``+matches=truth``. The thresholds file is keyed on these names.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from omniflow.config import PRESETS, OmniFlowConfig
from validation.variants import TrueMatches, omniflow_variants, variant_name

THRESHOLDS = Path(__file__).resolve().parents[2] / "validation" / "thresholds.toml"


def test_presets_are_named_by_the_preset_alone():
    for name in PRESETS:
        assert variant_name(OmniFlowConfig.preset(name)) == f"omniflow:{name}"


def test_other_configs_name_the_nearest_preset_and_the_changes():
    assert (
        variant_name(OmniFlowConfig(brightness={"brightness_model": "gain"}))
        == "omniflow:default+brightness.brightness_model=gain"
    )
    assert (
        variant_name(OmniFlowConfig.dense(pooling={"pool_k": 64}))
        == "omniflow:dense+pooling.pool_k=64"
    )
    assert variant_name(OmniFlowConfig.paper(band=0.5)) == "omniflow:paper+band=0.5"
    two = OmniFlowConfig(solver="direct", fit={"gradients": "first"})
    assert variant_name(two) == "omniflow:default+solver=direct+fit.gradients=first"
    assert variant_name(TrueMatches(OmniFlowConfig())) == "omniflow:default+matches=truth"
    assert variant_name(TrueMatches(OmniFlowConfig.paper())) == "omniflow:paper+matches=truth"


def test_all_rows_have_distinct_short_names():
    names = [n for n, _ in omniflow_variants("all")]
    assert len(set(names)) == len(names) == 19  # 16 combinations, the paper, 2 on truth
    assert names[0] == "omniflow:default"
    assert max(map(len, names)) <= 90  # main's paper row was 187 characters


def test_thresholds_name_rows_that_the_suite_scores():
    """Every omniflow method in thresholds.toml is a row of ``--variants all`` (mutation:
    the old bracketed names are caught)."""
    rows = {n for n, _ in omniflow_variants("all")}
    spec = tomllib.loads(THRESHOLDS.read_text())
    methods = {c["method"] for s in spec["scenes"].values() for c in s.get("check", [])}
    methods |= {c["method"] for s in spec["scenes"].values() for c in s.get("pending", [])}
    omni = {m for m in methods if m.startswith("omniflow")}
    assert omni and omni <= rows, sorted(omni - rows)
