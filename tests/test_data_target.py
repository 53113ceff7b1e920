"""The one target type: its forms, its refusals by name, its record as the store and the API keep it."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from comp_daemon.data.readers import parse_dataset
from comp_daemon.data.target import TARGET_FIELDS, Target, TargetError, targets_of_dataset
from comp_daemon.robot.description import load_robot
from comp_daemon.service.schemas import TargetIn

AXES = {"a1": 10.0, "a2": -80.0, "a3": 110.0, "a4": 0.0, "a5": 50.0, "a6": 0.0}


def test_axis_and_tcp_forms_and_their_records() -> None:
    by_axes = Target.from_record({"pose_id": "P1", **AXES, "payload_kg": 12})
    assert by_axes.axes_deg == (10.0, -80.0, 110.0, 0.0, 50.0, 0.0)
    assert by_axes.tcp_mm is None and by_axes.payload_kg == 12.0
    assert by_axes.to_record() == {"pose_id": "P1", **AXES, "payload_kg": 12.0}
    assert list(by_axes.to_record()) == [
        k for k in TARGET_FIELDS if k not in ("tx", "ty", "tz", "ta", "tb", "tc")
    ]
    oriented = Target(tcp_mm=(1500, 0, 1200), abc_deg=(0, 90, 0))
    assert oriented.to_record() == {"tx": 1500.0, "ty": 0.0, "tz": 1200.0, "ta": 0.0, "tb": 90.0, "tc": 0.0}
    assert all(type(v) is float for v in oriented.to_record().values())
    assert Target.from_record(oriented.to_record()) == oriented
    assert Target.from_record({"tx": 1.0, "ty": 2.0, "tz": 3.0, "ta": None}).abc_deg is None  # null: absent


@pytest.mark.parametrize(
    ("record", "words"),
    [
        ({"pose_id": "p1"}, "gives neither axis values a1..a6 nor a TCP tx, ty, tz"),
        ({"a1": 1.0, "tx": 2.0}, "a2, a3, a4, a5, a6 missing: axis values need all of a1, a2"),
        ({**AXES, "tx": 1.0, "ty": 2.0, "tz": 3.0}, "gives both axis values a1..a6 and a TCP"),
        ({"tx": 1.0, "ty": 2.0, "tz": 3.0, "ta": 0.0}, "tb, tc missing: an orientation needs all of ta"),
        ({**AXES, "a3": True}, "a3 must be a number, got True"),
        ({**AXES, "a3": "20"}, "a3 must be a number, got '20'"),
        ({**AXES, "a6": math.nan}, "a6 must be finite"),
        ({**AXES, "payload_kg": -1.0}, "payload_kg must be ≥ 0"),
        ({**AXES, "pose_id": ""}, "pose_id must be a non-empty string"),
        ({**AXES, "x": 1.0}, "unknown field 'x'"),
    ],
)
def test_a_record_that_is_not_a_target_is_refused_by_name(record: dict[str, object], words: str) -> None:
    with pytest.raises(TargetError, match="^" + re.escape(words)):
        Target.from_record(record)


def test_an_orientation_needs_a_tcp() -> None:
    # an orientation beside axis values is a second form, as the HTTP schema says
    with pytest.raises(TargetError, match=r"gives both axis values a1\.\.a6 and a TCP"):
        Target(axes_deg=tuple(AXES.values()), abc_deg=(0.0, 0.0, 0.0))
    with pytest.raises(TargetError, match="an orientation ta, tb, tc needs a TCP"):
        Target(abc_deg=(0.0, 0.0, 0.0))
    with pytest.raises(TargetError, match="tx, ty, tz: 3 values needed, got 2"):
        Target(tcp_mm=(1.0, 2.0))


def test_the_http_schema_and_a_target_file_give_the_same_target() -> None:
    body = {"pose_id": "h1", "tx": 1500.0, "ty": 100.0, "tz": 1200.0, "ta": 10.0, "tb": 80.0, "tc": -5.0}
    from_http = TargetIn.model_validate_json(
        '{"pose_id": "h1", "tx": 1500, "ty": 100, "tz": 1200, "ta": 10, "tb": 80, "tc": -5}'
    ).target()
    csv = "pose_id,tx,ty,tz,ta,tb,tc\nh1,1500,100,1200,10,80,-5\n"
    dataset = parse_dataset(
        csv.encode(), source="t.csv", limits_deg=load_robot("kr210").axis_limits_deg, kind="targets"
    )
    (from_file,) = targets_of_dataset(dataset)
    assert from_http == from_file == Target.from_record(body)
    assert from_http.to_record() == body


def test_a_target_file_with_payloads_keeps_only_those_given() -> None:
    csv = "pose_id,a1,a2,a3,a4,a5,a6,payload_kg\np1,10,-80,110,0,50,0,0\np2,10,-80,110,0,50,0,25\n"
    limits = load_robot("kr210").axis_limits_deg
    first, second = targets_of_dataset(
        parse_dataset(csv.encode(), source="t.csv", limits_deg=limits, kind="targets")
    )
    assert first.payload_kg is None and second.payload_kg == 25.0
    np.testing.assert_array_equal(first.axes_deg, list(AXES.values()))
