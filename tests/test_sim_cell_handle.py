"""The handle on the simulated cell (rt/simcell): scenario names without the simulator, the ready line."""

from __future__ import annotations

from pathlib import Path

import pytest

from comp_daemon import cli
from comp_daemon.sim.scenario import PRESET_SCENARIOS, load_scenario
from comp_daemon.sim_client import SimCellInfo, check_scenario, preset_scenarios


def test_presets_are_the_packaged_scenario_files() -> None:
    assert preset_scenarios() == PRESET_SCENARIOS
    assert {"kr210-cell", "kr210-geometric", "irb120-cell"} <= set(preset_scenarios())
    for name in preset_scenarios():
        assert load_scenario(name).source == f"preset:{name}"
        check_scenario(name)


def test_check_scenario_accepts_a_file_and_refuses_an_unknown_name(tmp_path: Path) -> None:
    path = tmp_path / "cell.toml"
    path.write_text("[scenario]\n", encoding="utf-8")
    check_scenario(str(path))
    with pytest.raises(ValueError, match=r"scenario 'kr211-cell': neither a preset \(.*kr210-cell.*\)"):
        check_scenario("kr211-cell")


def test_run_refuses_an_unknown_scenario_before_starting(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["run", "--sim", "--scenario", "no-such-cell"]) == 2
    assert "scenario 'no-such-cell'" in capsys.readouterr().err


def test_ready_line_round_trip() -> None:
    info = SimCellInfo(
        pid=7,
        motion_host="127.0.0.1",
        motion_port=4001,
        cell_host="127.0.0.1",
        cell_port=4002,
        rsi_local_port=4003,
        gratings={1: "/tmp/cell/grating-a1", 3: "/tmp/cell/grating-a3"},
        radius_mm=400.0,
        zero_deg=-200.0,
        resolution_nm=50.0,
        bits=26,
        home_deg=(0.0, -85.0, 125.0, 0.0, -40.0, 0.0),
        cycle_ms=12,
    )
    line = info.to_json()
    assert "\n" not in line
    assert SimCellInfo.from_json(line) == info
    assert SimCellInfo.from_json(line.encode()) == info
