"""The measuring parts of ``benchmarks.bench_jobs`` and ``benchmarks.bench_concurrent``: the CPU of a
process's descendants read from ``/proc``, the command line against an HTTP job, profiles compared
per function."""

from __future__ import annotations

import asyncio
import cProfile
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.bench_concurrent import compare_profiles, own_cpu
from benchmarks.bench_jobs import descendants_cpu_s, http_rounds
from comp_daemon.data.dataset import dataset_to_csv
from comp_daemon.sim.campaign import run_campaign
from comp_daemon.sim.scenario import load_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "comp_daemon" / "sim" / "scenarios"
# burns 0.3 s of CPU, writes a line, then waits to be killed
BURN = (
    "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\n"
    "print(1, flush=True)\ntime.sleep(60)\n"
)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_descendants_cpu_counts_children_and_grandchildren() -> None:
    starter = f"import subprocess, sys\nsubprocess.Popen([sys.executable, '-c', {BURN!r}])\n" + BURN
    child = subprocess.Popen([sys.executable, "-c", starter], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None
        assert child.stdout.readline() and child.stdout.readline()  # both have burnt their CPU
        mine = descendants_cpu_s(os.getpid())
        below_child = descendants_cpu_s(child.pid)
        assert mine[child.pid] >= 0.3
        assert len(below_child) == 1 and next(iter(below_child.values())) >= 0.3
        assert set(below_child) < set(mine)
        assert os.getpid() not in mine
    finally:
        for pid in descendants_cpu_s(child.pid):
            os.kill(pid, 9)
        child.kill()
        child.wait()
        if child.stdout is not None:
            child.stdout.close()


def test_profiles_compared_per_function(tmp_path, capsys) -> None:
    def work(n: int) -> float:
        return sum(i * 0.5 for i in range(n))

    for name, n in (("alone", 200_000), ("copy", 400_000)):
        prof = cProfile.Profile(time.process_time)
        prof.runcall(work, n)
        prof.dump_stats(tmp_path / f"{name}.prof")
    alone, copy = own_cpu(tmp_path / "alone.prof"), own_cpu(tmp_path / "copy.prof")
    key = max(alone, key=alone.__getitem__)  # the generator summed: twice the terms in the copy
    assert copy[key] > alone[key] > 0
    compare_profiles(tmp_path / "alone.prof", [tmp_path / "copy.prof"], top=3)
    assert "the costliest functions alone" in capsys.readouterr().out


def test_a_fit_job_over_http_against_the_command_line(tmp_path) -> None:
    ds = run_campaign(load_scenario(str(SCENARIOS / "kr210-cell.toml")), 120, seed=5)
    data = tmp_path / "c.csv"
    data.write_text(dataset_to_csv(ds))
    jobs = {"cpus": [], "nice": 0}
    rows = asyncio.run(http_rounds("fit", data, "kr210", "kinematic", 2, jobs))
    assert [r["job_first"] for r in rows] == [False, True]
    for r in rows:
        for path in ("cli", "job"):
            assert r[path]["wall_s"] > 0 and r[path]["cpu_s"] > 0
        assert r["job"]["worker_cpu_s"] > 0  # the fit ran in the pool's worker, counted from /proc
        assert r["job"]["cpu_s"] == pytest.approx(r["job"]["worker_cpu_s"] + r["job"]["service_cpu_s"])
