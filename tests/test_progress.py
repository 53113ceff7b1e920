"""Progress of the long commands: drawn on a terminal (a pseudo-terminal here), silent otherwise."""

from __future__ import annotations

import json
import os
import pty
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.data.dataset import Dataset, write_dataset
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.robot.description import load_robot

ROOT = Path(__file__).resolve().parents[1]
KR = load_robot("kr210")


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(2)
    n = 90
    lim = KR.axis_limits_deg
    a = lim.mean(axis=1) + rng.uniform(-0.5, 0.5, (n, 6)) * np.minimum((lim[:, 1] - lim[:, 0]) / 2, 90.0)
    dirs = rng.choice([-1, 1], size=(n, 6))
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros().with_values(["h2"], [0.005])
    p = twin_tcp_mm(KR, truth, eff, a, dirs.astype(float)) + rng.normal(size=(n, 3)) * 0.01
    path = tmp_path_factory.mktemp("progress") / "campaign.csv"
    write_dataset(
        Dataset(a_deg=a, xyz_mm=p, dir=dirs, split=np.where(np.arange(n) < 60, "fit", "check")), path
    )
    return path


def _commands(data: Path, out: Path) -> dict[str, list[str]]:
    robot = ["--robot", "kr210"]
    return {
        "evaluate": ["evaluate", str(data), *robot, "--models", "nominal,kinematic"],
        "fit": ["fit", str(data), *robot, "--model", "kinematic", "--out", str(out / "m.json")],
        "diagnose": ["diagnose", str(data), *robot, "--effects", "backlash", "--json", str(out / "d.json")],
    }


def _run(argv: list[str], terminal: bool) -> tuple[int, str, str]:
    """Run ``comp-daemon argv``; stderr a pseudo-terminal or a pipe. Returns code, stdout, stderr."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "120", "FORCE_COLOR": "1"}
    cmd = [sys.executable, "-m", "comp_daemon", *argv]
    if not terminal:
        done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
        return done.returncode, done.stdout, done.stderr
    master, slave = pty.openpty()
    chunks: list[bytes] = []

    def drain() -> None:
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # the child closed its end
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain)
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=slave, env=env, text=True) as proc:
        os.close(slave)
        reader.start()
        stdout, _ = proc.communicate(timeout=300)
    reader.join(timeout=10)
    os.close(master)
    return proc.returncode, stdout, b"".join(chunks).decode("utf-8", "replace")


@pytest.mark.parametrize("command", ["evaluate", "fit", "diagnose"])
def test_progress_only_on_a_terminal(campaign: Path, tmp_path: Path, command: str) -> None:
    argv = _commands(campaign, tmp_path)[command]
    code, out, err = _run(argv, terminal=False)
    assert code == 0, err
    assert err == ""  # FORCE_COLOR is set, yet a pipe gets nothing
    code, out_tty, err_tty = _run(argv, terminal=True)
    assert code == 0, err_tty
    assert "\x1b[" not in out_tty and out_tty.splitlines()[0] == out.splitlines()[0]  # stdout untouched
    assert "\x1b[" in err_tty  # drawn with terminal escapes
    assert "0:00:" in err_tty  # the elapsed time
    expected = {
        "evaluate": "fitting kinematic on 60 rows",
        "fit": "fitting kinematic",
        "diagnose": "diagnosing 90 rows",
    }
    assert expected[command] in err_tty
    if command == "evaluate":
        assert "2/2" in err_tty and "kinematic: check RMS" in err_tty


def test_evaluate_says_which_model_is_fitted_and_how_many_remain(campaign: Path, tmp_path: Path) -> None:
    """Serially and with ``--jobs 2`` (the models fitted in two processes): the same table."""
    tables = {}
    for jobs in ("1", "2"):
        out_json = tmp_path / f"evaluate-{jobs}.json"
        argv = ["evaluate", str(campaign), "--robot", "kr210", "--models", "nominal,kinematic,chebyshev:1"]
        code, _, err = _run([*argv, "--jobs", jobs, "--json", str(out_json)], terminal=True)
        assert code == 0, err
        assert "models left)" in err  # each model's line says how many remain
        if jobs == "1":
            assert "fitting kinematic on 60 rows (2 of 3, 1 after it)" in err
        else:
            assert "3 models on 2 processes" in err
        tables[jobs] = json.loads(out_json.read_text())["table2"]
    assert tables["1"].keys() == tables["2"].keys()
    for name in tables["1"]:
        assert tables["2"][name]["3d"]["rms"] == pytest.approx(tables["1"][name]["3d"]["rms"], rel=1e-12)


def test_evaluate_jobs_refuses_what_is_not_a_count() -> None:
    code, _, err = _run(["evaluate", "x.csv", "--robot", "kr210", "--jobs", "two"], terminal=False)
    assert code == 2 and "--jobs" in err and "number of processes" in err


def test_the_terminal_follows_the_steps_of_a_fit(campaign: Path) -> None:
    """A fit that selects by cross-validation shows its fits as they are made, after what it fits."""
    argv = ["evaluate", str(campaign), "--robot", "kr210", "--models", "chebyshev:cv"]
    code, _, err = _run(argv, terminal=True)
    assert code == 0, err
    assert "fitting chebyshev:cv on 60 rows (1 of 1, 0 after it): cross-validation fits" in err
    assert " of 50" in err  # five orders, two thresholds, five folds
