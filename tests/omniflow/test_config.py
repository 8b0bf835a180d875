"""OmniFlowConfig's presets, public knobs and nested expert groups (omniflow.config)."""

from __future__ import annotations

import pytest

from omniflow.config import (
    DEPENDENCIES,
    GROUPS,
    PRESETS,
    PUBLIC_FIELDS,
    OmniFlowConfig,
    knob_fields,
    nested,
)


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


#: A value away from each dependent knob's default, and the needed knob's off value.
OFF = {
    "pooling.static_test": None,
    "iterations": 0,
    "matching.consistency": None,
    "matching.alias_score": None,
    "matching.edge_smooth": None,
    "decouple_tol": None,
    "brightness.flow_shading": None,
    "brightness_gate": None,
    "fit.temporal": "difference",
}
SET = {"pooling.static_max_px": 0.5, "refinement.iterate_min_px": 0.0,
       "matching.consistency_support": 3, "matching.alias_image2": -1.0,
       "matching.alias_period": 0.5, "matching.edge_smooth_floor": None,
       "brightness.decouple_gain_tol": None, "brightness.flow_shading_where": "moving",
       "brightness.brightness_model": "gain", "fit.temporal_frames": 5}  # fmt: skip


@pytest.mark.parametrize(("name", "needs"), [d[:2] for d in DEPENDENCIES])
def test_an_inert_knob_is_an_error_naming_both(name, needs):
    """A knob set while the knob it needs is off names both; with that knob on, or at its
    default, the same config is made (mutation caught: a check that ignored ``needs``)."""
    with pytest.raises(ValueError, match=rf"OmniFlowConfig.{name} = .* with {needs} = "):
        OmniFlowConfig().with_settings({name: SET[name], needs: OFF[needs]})
    OmniFlowConfig().with_settings({needs: OFF[needs]})
    on = {"pooling.static_test": 2.0, "iterations": 1, "fit.temporal": "dct3d",
          "brightness.flow_shading": 4.0}  # fmt: skip
    OmniFlowConfig().with_settings(
        {name: SET[name], needs: on.get(needs, knob_fields()[needs].default)}
    )


@pytest.mark.parametrize("name", list(PRESETS))
def test_presets_set_no_inert_knob(name):
    """Every preset is made (no knob of DEPENDENCIES set while the knob it needs is off)."""
    assert isinstance(OmniFlowConfig.preset(name), OmniFlowConfig)


def test_a_group_field_given_flat_names_its_group():
    with pytest.raises(TypeError, match=r"OmniFlowConfig.pool_k: no such knob; it is pooling"):
        OmniFlowConfig(pool_k=3)
    with pytest.raises(TypeError, match=r"OmniFlowConfig.pool_kk: no such knob$"):
        OmniFlowConfig(pool_kk=3)
