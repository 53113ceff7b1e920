"""Robot description files: presets load, and every kind of bad file is refused with a clear message."""

from __future__ import annotations

from pathlib import Path

import pytest

from comp_daemon.cli import main
from comp_daemon.robot.description import PRESETS, RobotDescriptionError, load_robot, parse_robot_toml

GOOD_JOINT = """
[[joint]]
a_mm = 100.0
alpha_deg = -90.0
d_mm = 500.0
beta_deg = 0.0
sign = 1
offset_deg = 0.0
min_deg = -170.0
max_deg = 170.0
mass_kg = 10.0
com_mm = [0.0, 0.0, 0.0]
"""
HEAD = '[robot]\nname = "Test arm"\nrepeatability_mm = 0.05\n[tool]\nxyz_mm = [0.0, 0.0, 100.0]\n'


def _file(joints: list[str], head: str = HEAD) -> str:
    return head + "".join(joints)


@pytest.mark.parametrize("name", list(PRESETS))
def test_presets_load(name: str) -> None:
    robot = load_robot(name)
    assert robot.name == PRESETS[name]
    assert len(robot.joints) == 6
    assert len(robot.sha256) == 64


def test_a_good_file_loads_and_hash_ignores_formatting() -> None:
    text = _file([GOOD_JOINT] * 6)
    a = parse_robot_toml(text)
    b = parse_robot_toml("# a comment\n" + text.replace(" = ", "="))
    assert a.sha256 == b.sha256


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (_file([GOOD_JOINT] * 5), "5 \\[\\[joint\\]\\] tables; six joints are expected"),
        (_file([GOOD_JOINT] * 7), "7 \\[\\[joint\\]\\] tables"),
        (
            _file([GOOD_JOINT.replace("a_mm = 100.0\n", "")] + [GOOD_JOINT] * 5),
            "joint 1: missing field 'a_mm'",
        ),
        (
            _file([GOOD_JOINT] * 2 + [GOOD_JOINT.replace("alpha_deg", "alpha_rad")] + [GOOD_JOINT] * 3),
            "joint 3: field 'alpha_rad' is in rad; this format expects 'alpha_deg'",
        ),
        (_file([GOOD_JOINT.replace("d_mm", "d_m")] + [GOOD_JOINT] * 5), "field 'd_m' is in m"),
        (
            _file([GOOD_JOINT.replace("sign = 1", "sign = 2")] + [GOOD_JOINT] * 5),
            "joint 1.sign: must be 1 or -1",
        ),
        (
            _file([GOOD_JOINT.replace("min_deg = -170.0", "min_deg = 200.0")] + [GOOD_JOINT] * 5),
            "min_deg \\(200.0\\) must be below max_deg",
        ),
        (
            _file([GOOD_JOINT.replace("a_mm = 100.0", 'a_mm = "long"')] + [GOOD_JOINT] * 5),
            "a_mm: expected a number",
        ),
        (
            _file([GOOD_JOINT.replace("a_mm = 100.0", "a_mm = nan")] + [GOOD_JOINT] * 5),
            "expected a finite number",
        ),
        (
            _file([GOOD_JOINT.replace("com_mm = [0.0, 0.0, 0.0]", "com_mm = [0.0, 0.0]")] + [GOOD_JOINT] * 5),
            "com_mm: expected a list of three numbers",
        ),
        (_file([GOOD_JOINT + "colour = 'orange'\n"] + [GOOD_JOINT] * 5), "unknown field 'colour'"),
        (
            _file([GOOD_JOINT] * 6, head=HEAD.replace("repeatability_mm = 0.05\n", "")),
            "missing field 'repeatability_mm'",
        ),
        (
            _file(
                [GOOD_JOINT] * 6,
                head=HEAD.replace("[tool]\nxyz_mm = [0.0, 0.0, 100.0]", "[tool]\nxyz_in = [0, 0, 4]"),
            ),
            "field 'xyz_in' is in in",
        ),
        ("[robot\nname=", "not valid TOML"),
        (HEAD, "missing \\[\\[joint\\]\\] tables"),
    ],
)
def test_bad_files_are_refused_by_name(text: str, match: str) -> None:
    with pytest.raises(RobotDescriptionError, match=match):
        parse_robot_toml(text)


def test_unknown_preset_or_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RobotDescriptionError, match="neither a preset"):
        load_robot("kr999")
    bad = tmp_path / "arm.toml"
    bad.write_text(_file([GOOD_JOINT] * 4))
    with pytest.raises(RobotDescriptionError, match=str(bad)):
        load_robot(bad)


def test_cli_show_accepts_a_path_and_refuses_a_bad_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = tmp_path / "arm.toml"
    good.write_text(_file([GOOD_JOINT] * 6))
    assert main(["robot", "show", str(good)]) == 0
    assert '"Test arm"' in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text(_file([GOOD_JOINT] * 3))
    assert main(["robot", "show", str(bad)]) == 2
    assert "six joints are expected" in capsys.readouterr().err


@pytest.mark.parametrize("suffix", [".toml", ".urdf"])
def test_a_file_that_is_not_utf8_is_refused_by_its_path(tmp_path: Path, suffix: str) -> None:
    bad = tmp_path / f"arm{suffix}"
    bad.write_bytes(b'[robot]\nname = "\xff\xfe"\n')
    with pytest.raises(RobotDescriptionError, match=f"^{bad}: cannot read: 'utf-8' codec"):
        load_robot(bad)
