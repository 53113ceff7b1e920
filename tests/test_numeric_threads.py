"""The numeric libraries' threads are set on purpose: by the command line before NumPy loads
(``--threads``, ``COMP_DAEMON_THREADS``, default 1) and in every job worker (``jobs.threads``),
whatever the environment the process was started with; the job pool has a worker per CPU it may
use."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from comp_daemon.common.threads import THREAD_VARIABLES, threads_from_argv
from comp_daemon.service.config import JobSettings
from comp_daemon.service.jobs import JobKind, JobRunner
from comp_daemon.service.store import Store

ROOT = Path(__file__).resolve().parents[1]


def blas_threads(*, progress: Callable[..., None]) -> dict[str, Any]:
    """(In a worker) the thread counts of the numeric libraries it loaded, and its environment's."""
    import numpy as np

    from comp_daemon.common.threads import numeric_threads

    np.linalg.qr(np.ones((50, 5)))  # make sure BLAS is loaded and used
    return {"threads": numeric_threads(), "env": os.environ.get("OPENBLAS_NUM_THREADS")}


def _blas(threads: dict[str, int]) -> list[int]:
    counts = [n for name, n in threads.items() if name.endswith(":blas")]
    assert counts, f"no BLAS library found: {threads}"
    return counts


def _child_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES and k != "COMP_DAEMON_THREADS"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")])
    env.update(extra)
    return env


_PROBE = """
import json, sys, types
import comp_daemon.cli as cli

def probe(args):  # a command that loads NumPy only when it runs, as the real ones may
    import numpy as np
    from comp_daemon.common.threads import numeric_threads
    np.linalg.qr(np.ones((50, 5)))
    print(json.dumps(numeric_threads()))
    return 0

def register(subparsers):
    subparsers.add_parser("probe").set_defaults(func=probe)

module = types.ModuleType("threads_probe")
module.register = register
sys.modules["threads_probe"] = module
cli.COMMAND_MODULES = {"probe": "threads_probe"}
assert "numpy" not in sys.modules
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.parametrize(
    ("argv", "env", "expected"),
    [
        ([], {"OPENBLAS_NUM_THREADS": "3", "OMP_NUM_THREADS": "3"}, 1),  # the default, not the env's
        (["--threads", "2"], {}, 2),
        (["--threads=2"], {"OPENBLAS_NUM_THREADS": "1"}, 2),
        ([], {"COMP_DAEMON_THREADS": "2"}, 2),
    ],
)
def test_the_command_line_sets_the_threads_before_numpy_loads(
    argv: list[str], env: dict[str, str], expected: int
) -> None:
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, *argv, "probe"],
        env=_child_env(**env),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert set(_blas(json.loads(out.stdout.strip().splitlines()[-1]))) == {expected}


def test_a_bad_thread_count_is_refused_by_name() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "comp_daemon", "--threads", "0", "robot", "show", "kr210"],
        env=_child_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2
    assert "--threads" in out.stderr and "1..256" in out.stderr


def test_threads_from_argv_reads_only_the_options_before_the_command() -> None:
    assert threads_from_argv(["--threads", "4", "evaluate", "x.csv"]) == 4
    assert threads_from_argv(["evaluate", "x.csv", "--threads", "4"]) == 1
    with pytest.raises(ValueError, match="--threads"):
        threads_from_argv(["--threads", "many"])


@pytest.mark.parametrize("threads", [1, 2])
async def test_every_job_worker_sets_its_threads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threads: int
) -> None:
    # the daemon started with an environment asking for more threads than the setting
    for name in THREAD_VARIABLES:
        monkeypatch.setenv(name, "4")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), str(ROOT / "tests")]))
    store = Store(tmp_path / "s.sqlite3")
    runner = JobRunner(store, JobSettings(workers=1, threads=threads))
    runner.register(JobKind("blas", blas_threads))
    runner.start()
    try:
        job = store.create_job("blas", {})
        await asyncio.to_thread(runner.launch, job, ())
        for _ in range(1200):
            if store.get_job(job.id).state not in ("queued", "running"):
                break
            await asyncio.sleep(0.05)
        await runner.drain()
        done = store.get_job(job.id)
        assert done.state == "done", done.error
        assert done.result is not None
        assert set(_blas(done.result["threads"])) == {threads}
        assert done.result["env"] == str(threads)  # and what the worker's children would load
    finally:
        runner.shutdown()
        store.close()


def test_the_job_pool_takes_the_cpus_it_may_use(tmp_path: Path) -> None:
    """``jobs.workers = 0`` (the default): one worker per CPU of ``jobs.cpus``, or every CPU but the
    real-time one; a number is taken as it is."""
    store = Store(tmp_path / "s.sqlite3")
    try:
        assert JobSettings().workers == 0
        assert JobRunner(store, JobSettings(cpus=[1])).workers == 1
        assert JobRunner(store, JobSettings(cpus=[0, 2, 3])).workers == 3
        assert JobRunner(store, JobSettings(workers=2, cpus=[1])).workers == 2
        every = len(os.sched_getaffinity(0))
        assert JobRunner(store, JobSettings()).workers == max(1, every - 1)
    finally:
        store.close()
