"""The daemon and the commands run without the simulator, the trial without the daemon's internals.

Each check imports every module of the packages in a fresh interpreter and looks at ``sys.modules``
afterwards, so an import anywhere (at module level) that pulls the forbidden package in fails.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

PROBE = """
import importlib, json, pkgutil, sys
import comp_daemon
names = sys.argv[1].split(",")
for name in names:
    package = importlib.import_module(name)
    for info in pkgutil.walk_packages(package.__path__, name + "."):
        importlib.import_module(info.name)
print(json.dumps(sorted(sys.modules)))
"""


def _loaded_after_importing(*packages: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, ",".join(packages)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    loaded: list[str] = json.loads(out.stdout)
    assert all(p in loaded for p in packages)
    return loaded


def _under(loaded: list[str], package: str) -> list[str]:
    return [m for m in loaded if m == package or m.startswith(package + ".")]


@pytest.mark.parametrize(
    ("packages", "handle"),
    [
        (("comp_daemon.daemon",), "comp_daemon.daemon.simcell"),
        (("comp_daemon.commands",), "comp_daemon.commands.run"),
    ],
)
def test_daemon_and_commands_import_without_the_simulator(packages: tuple[str, ...], handle: str) -> None:
    loaded = _loaded_after_importing(*packages)
    assert handle in loaded and "comp_daemon.sim_client" in loaded
    assert _under(loaded, "comp_daemon.sim") == []


def test_trial_imports_without_the_daemon() -> None:
    loaded = _loaded_after_importing("comp_daemon.trial")
    assert _under(loaded, "comp_daemon.daemon") == []
    assert "comp_daemon.trial.runner" in loaded and "comp_daemon.sim_client" in loaded


def test_cli_loads_the_simulator_only_for_the_sim_command() -> None:
    probe = (
        "import sys, contextlib, io\n"
        "from comp_daemon import cli\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    code = cli.main(sys.argv[1:])\n"
        "print(code, any(m == 'comp_daemon.sim' or m.startswith('comp_daemon.sim.') for m in sys.modules))\n"
    )

    def run(*argv: str) -> str:
        out = subprocess.run(
            [sys.executable, "-c", probe, *argv], capture_output=True, text=True, check=True, timeout=120
        )
        return out.stdout.strip().splitlines()[-1]

    assert run("robot", "show", "kr210") == "0 False"
    assert run("sim", "report", "--n", "12", "--cycles", "2", "--json") == "0 True"
