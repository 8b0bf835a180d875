"""OmniFlowConfig's presets, public knobs and nested expert groups (omniflow.config)."""

from __future__ import annotations

import pytest

from omniflow.config import GROUPS, PRESETS, PUBLIC_FIELDS, OmniFlowConfig, knob_fields, nested


def test_a_small_public_surface():
    """At most 15 public knobs; every other knob sits in one group, under one dotted name."""
    assert len(PUBLIC_FIELDS) <= 15
    names = list(knob_fields())
    assert len(names) == len(set(names))
    assert [n for n in names if "." not in n] == list(PUBLIC_FIELDS)
    assert {n.partition(".")[0] for n in names if "." in n} == set(GROUPS)


def test_a_group_mapping_changes_only_its_named_fields():
    """``pooling={"pool_k": 64}`` on the dense preset keeps its grid pools (mutation caught:
    a mapping that replaced the whole group would bring back the default's k-d tree)."""
    dense = OmniFlowConfig.preset("dense", pooling={"pool_k": 64})
    assert dense.pooling.pool_k == 64
    assert dense.pooling.pool_grid == OmniFlowConfig.dense().pooling.pool_grid == 0.125
    assert dense.brightness == OmniFlowConfig.dense().brightness
    assert dense == OmniFlowConfig.dense().with_settings({"pooling.pool_k": 64})
    assert OmniFlowConfig(pooling={"pool_k": 64}).pooling.pool_grid is None


@pytest.mark.parametrize("name", list(PRESETS))
def test_dotted_settings_round_trip(name):
    """to_dict's dotted names rebuild the config (the names of --set and of row names)."""
    config = OmniFlowConfig.preset(name)
    assert OmniFlowConfig().with_settings(config.to_dict()) == config
    assert nested({"band": 0.3, "fit.flow_taper": 0.0}) == {"band": 0.3, "fit": {"flow_taper": 0.0}}


def test_bad_names_and_values_name_the_knob():
    with pytest.raises(ValueError, match=r"OmniFlowConfig.pooling.pool_kk: no such option"):
        OmniFlowConfig(pooling={"pool_kk": 3})
    with pytest.raises(ValueError, match=r"OmniFlowConfig.pool_k: no such knob; it is pooling"):
        OmniFlowConfig().replace(pool_k=3)
    with pytest.raises(ValueError, match=r"OmniFlowConfig.matching.min_score = 2: expected"):
        OmniFlowConfig(matching={"min_score": 2})
    with pytest.raises(ValueError, match=r"OmniFlowConfig.fit = 3: expected a FitOptions"):
        OmniFlowConfig(fit=3)


def test_a_combination_that_cannot_work_names_both_knobs():
    with pytest.raises(ValueError, match=r"pooling.pool_grid = 0.125 with brightness.brightness_m"):
        OmniFlowConfig(pooling={"pool_grid": 0.125})
