"""One place per convention: the kind lists are the registry's, the clock's effects the catalogue's,
an MDH geometry is stored one way, the joint mapping is named after what it does."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.diagnosis import ladder
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models import artifact
from comp_daemon.models.compensation import RENAMED_MAPPINGS, compensate
from comp_daemon.models.compliance import ComplianceModel
from comp_daemon.models.effects import EFFECT_CATALOGUE, TIME_EFFECTS, TRANSMISSION_EFFECTS
from comp_daemon.models.kinematic import MDH_FIELDS, KinematicModel, params_from_payload
from comp_daemon.models.registry import ARTIFACT_KINDS, KINDS, parse_model_name
from comp_daemon.robot.description import load_robot
from comp_daemon.service.schemas import FitIn

KR = load_robot("kr210")


def test_the_fit_request_names_every_kind_of_the_registry() -> None:
    description = FitIn.model_fields["model"].description or ""
    named = description.split("(", 1)[1].split(")", 1)[0].split(", ")
    assert named == list(KINDS)  # poe included
    assert "poe" in ARTIFACT_KINDS and "ARTIFACT_KINDS" in (artifact.__doc__ or "")


def test_the_time_effects_are_the_catalogues_clock_effects() -> None:
    clocked = [e.name for e in EFFECT_CATALOGUE if "clock" in e.required]
    assert list(TIME_EFFECTS) == clocked and clocked
    assert ladder.TIME_EFFECTS is TIME_EFFECTS
    assert all(not e.of_the_robot for e in EFFECT_CATALOGUE if e.name in TIME_EFFECTS)
    # the kriging-backlash kind stacks the transmission's effects
    assert parse_model_name("kriging-backlash").kind == "kriging-backlash"
    assert TRANSMISSION_EFFECTS == ("ratio", "backlash")


def test_an_mdh_geometry_is_stored_one_way() -> None:
    nominal = KinematicParams.from_robot(KR)
    params = nominal.apply(np.linspace(-1e-3, 1e-3, 39))
    kinematic = KinematicModel(KR, params, None, np.eye(4)).to_payload()
    compliance = ComplianceModel(
        KR, np.zeros(6), np.zeros(6), params.world_T_base, params.tool_xyz_mm, np.eye(4), params
    ).to_payload()
    assert {k: kinematic[k] for k in MDH_FIELDS} == compliance["mdh"]
    back = params_from_payload(KR, compliance["mdh"], compliance["tool_xyz_mm"], compliance["world_T_base"])
    for name in MDH_FIELDS:
        np.testing.assert_array_equal(getattr(back, name), getattr(params, name))
    broken = dict(compliance["mdh"], d_mm=[0.0] * 5)
    with pytest.raises(ValueError, match=r"'mdh\.d_mm': expected shape"):
        ComplianceModel.from_payload(KR, {**compliance, "mdh": broken}, None, np.eye(4))


def test_the_former_mapping_name_is_refused_in_code_with_the_new_one() -> None:
    assert RENAMED_MAPPINGS == {"seed000": "three-axis"}
    model = KinematicModel(KR, KinematicParams.from_robot(KR), None, np.eye(4))
    with pytest.raises(ValueError, match="mapping 'seed000' is now called 'three-axis'"):
        compensate(model, np.array([[1800.0, 0.0, 1200.0]]), mapping="seed000")  # type: ignore[arg-type]
