"""Each friction law has one constructor of its preset mapping (``element``), and what it writes
is a valid element of that law."""
from __future__ import annotations

import pytest

from stage_sim import friction
from stage_sim.config import load_preset, preset_from_dict

ARGS = {
    "dahl": dict(k_sigma=2.19e6, f_c=5.31),
    "gms": dict(k=[1e5, 2e5], alpha=[0.4, 0.6], f_c=5.31),
    "lugre": dict(sigma0=2.19e6, f_c=5.31, f_s=8.0, v_s=1e-3, sigma1=500.0),
    "coulomb": dict(f_c=5.31),
    "regularized_coulomb": dict(f_c=5.31, v_reg=1e-4),
    "gms_rate_state": dict(k=[1e5, 2e5], alpha=[0.4, 0.6], f_c=5.31, a=0.02),
}


@pytest.mark.parametrize("law", friction.LAWS, ids=lambda m: m.NAME)
def test_each_law_constructs_a_valid_element_of_itself(law):
    el = law.element(**ARGS[law.NAME], viscous=3.0, f_c_difference=0.4)
    assert el["model"] == law.NAME
    cfg = law.Schema.model_validate(el)
    assert cfg.viscous == 3.0 and cfg.f_c_difference == 0.4 and cfg.f_c == 5.31
    # and as a bearing's friction of a preset
    d = load_preset("fi_stage_nofi").model_dump(mode="json")
    d["stage"]["bearings"][0]["friction"] = el
    assert preset_from_dict(d).stage.bearings[0].friction.model == law.NAME


def test_an_unknown_variation_field_is_refused():
    with pytest.raises(TypeError, match="f_c_slope"):
        friction.dahl.element(2.19e6, 5.31, f_c_slope=1.0)
