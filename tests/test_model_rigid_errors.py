"""The rigid-body model rejects what it cannot evaluate with the project's typed error, naming the joint, the field
and the value (a bad pack or a wrong-length input must say what is wrong, not surface as a bare ValueError)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from msk_core.errors import ModelError
from msk_core.model import load_pack
from msk_core.model.rigid import RigidModel


def test_an_unknown_joint_kind_names_the_joint_and_the_kind():
    pack = load_pack("arm26")
    description = copy.deepcopy(pack.raw["dynamics"])
    description["joints"][1]["kind"] = "spherical"
    name = description["joints"][1]["name"]
    with pytest.raises(ModelError, match=rf"joint '{name}' \(dynamics.joints\[1\].kind\) is 'spherical'"):
        RigidModel(description, n_coordinates=len(pack.coordinates))


def test_the_compiled_evaluator_names_the_input_of_the_wrong_shape():
    pack = load_pack("arm26")
    rigid = RigidModel(pack.raw["dynamics"], n_coordinates=len(pack.coordinates), compiled=True)
    n = len(pack.coordinates)
    ok = np.zeros(n)
    assert rigid.inverse_dynamics(ok, ok, ok, 0.0, None).shape == (n,)
    with pytest.raises(
        ModelError, match=rf"qdd must have shape \({n},\) \(one value per coordinate\), got \({n + 1},\)"
    ):
        rigid.inverse_dynamics(ok, ok, np.zeros(n + 1), 0.0, None)
    with pytest.raises(ModelError, match=r"gravity must be a 3-vector \(m/s²\), got shape \(2,\)"):
        rigid.inverse_dynamics(ok, ok, ok, 0.0, np.array([0.0, -9.8]))
