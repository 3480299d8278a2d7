"""The model effects' names and coefficient keys: one name per effect across the generator and the estimator, a
profile written with a former name still loads, and the written form of the coefficient keys."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msk_core.errors import EstimationError
from msk_core.estimate.effects import (
    EFFECTS_FORMAT_VERSION,
    FORMER_EFFECT_NAMES,
    CoefKey,
    Effect,
    ModelEffects,
    Nuisance,
    torque_term_names,
)
from msk_core.synth.effects import Effects

GROUPS, COORDINATES = ["BIClong", "TRIlong"], ["r_shoulder_elev", "r_elbow_flex"]


def _section(*effects: tuple[str, dict]) -> dict:
    return {
        "format_version": EFFECTS_FORMAT_VERSION,
        "effects": [{"name": n, "parameters": p} for n, p in effects],
        "strength_gain": {},
        "evidence": {},
    }


def test_the_generator_names_each_effect_as_the_estimator_does():
    """Every hidden effect of ``msk synth`` that the torque model can describe has the model's name for it (``fatigue``
    changes the EMG spectrum only); the two former names for the bar's misreported load are one now."""
    generator = {f.name for f in dataclasses.fields(Effects)}
    assert generator - {"fatigue"} <= {e.value for e in Effect}, generator - {e.value for e in Effect}
    assert "load_misreport" in generator and Effect.LOAD_MISREPORT.value == "load_misreport"
    assert not set(FORMER_EFFECT_NAMES) & {e.value for e in Effect}
    # a coefficient's term is an effect or a nuisance term, told apart by value (both are string enums)
    assert not {e.value for e in Effect} & {n.value for n in Nuisance}


def test_a_profile_with_the_former_load_scale_name_loads_as_load_misreport():
    former = ModelEffects.from_dict(_section(("load_scale", {"true_over_reported": 0.8})), GROUPS, COORDINATES)
    current = ModelEffects.from_dict(_section(("load_misreport", {"true_over_reported": 0.8})), GROUPS, COORDINATES)
    assert former.names == current.names == [Effect.LOAD_MISREPORT]
    assert former.load_ratio == current.load_ratio == 0.8
    assert former.to_dict()["effects"] == [{"name": "load_misreport", "parameters": {"true_over_reported": 0.8}}]
    assert ModelEffects.from_dict(_section(), GROUPS, COORDINATES).load_ratio == 1.0


@pytest.mark.parametrize(
    ("effects", "message"),
    [
        ([{"name": "load_scaling", "parameters": {}}], r"effects.effects: unknown effect 'load_scaling'; known: emd"),
        ([{"name": 3, "parameters": {}}], r"unknown effect 3"),
        ([{"name": "damping"}], r"effects.effects: malformed effect"),
        (["damping"], r"effects.effects: malformed effect 'damping'"),
    ],
)
def test_an_unknown_or_malformed_effect_is_named_in_the_error(effects, message):
    with pytest.raises(EstimationError, match=message):
        ModelEffects.from_dict(dict(_section(), effects=effects), GROUPS, COORDINATES)


def test_coefficient_keys_are_written_in_one_readable_form():
    """The calibration report's torque-basis table and the discrepancy summary name the coefficients this way."""
    model = {Effect.FL_PASSIVE: {"strain": 0.6}, Effect.PASSIVE_JOINT: {"decay_rad": 0.2}, Effect.DAMPING: {}}
    assert [str(k) for k in torque_term_names(model, COORDINATES)] == [
        "fl_passive:scale",
        "passive_joint:k_lower:r_shoulder_elev",
        "passive_joint:k_upper:r_shoulder_elev",
        "passive_joint:k_lower:r_elbow_flex",
        "passive_joint:k_upper:r_elbow_flex",
        "damping:b:r_shoulder_elev",
        "damping:b:r_elbow_flex",
    ]
    assert str(CoefKey(Nuisance.GAIN, group="BIClong")) == "gain:BIClong"
    assert str(CoefKey(Nuisance.DEMAND, group="BIClong", phase_bin=0)) == "demand:BIClong:0"
    assert str(CoefKey(Nuisance.OFFSET, coordinate="r_elbow_flex")) == "offset:r_elbow_flex"
    arm = CoefKey(Effect.MOMENT_ARM_SCALE, "scale", group="BIClong", coordinate="r_elbow_flex")
    assert str(arm) == "moment_arm_scale:scale:BIClong:r_elbow_flex"
    # keys compare by their parts (the discrepancy fit looks coefficients up by key)
    assert arm == CoefKey(Effect.MOMENT_ARM_SCALE, "scale", group="BIClong", coordinate="r_elbow_flex")
    assert len({arm, CoefKey(Effect.MOMENT_ARM_SCALE, "scale", group="TRIlong", coordinate="r_elbow_flex")}) == 2
    assert np.array_equal([k.coordinate for k in torque_term_names({Effect.DAMPING: {}}, COORDINATES)], COORDINATES)
