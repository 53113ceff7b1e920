"""A diagnosis and a fit as the daemon runs them (a job in its worker pool: a spawned, niced process
off the real-time CPU) against the same work in the command line's process, on the same data.

``python -m benchmarks.bench_jobs --data CAMPAIGN.csv --robot kr210 [--kind diagnosis|fit]
[--model NAME] [--cpus 0] [--nice 10] [--threads 1]``

Prints, for each path, the wall time and the CPU time of the process that did the work (the job's
worker measures its own), and the load average. ``--threads 0`` leaves the worker's numeric
libraries at their default (a thread per core), as the pool did before it set them.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.machine import machine_line
from comp_daemon.common.threads import numeric_threads, set_numeric_threads


def timed_job(
    kind: str, args: tuple[Any, ...], default_threads: bool = False, *, progress: Any
) -> dict[str, Any]:
    """(In the worker) the job kind's function, with the worker's CPU time and its BLAS threads;
    ``default_threads``: with the numeric libraries' own default, a thread per core (as before the
    pool set them)."""
    from comp_daemon.service import job_kinds

    if default_threads:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=os.cpu_count())

    func = {"diagnosis": job_kinds.run_diagnosis, "fit": job_kinds.run_fit}[kind]
    c0, t0 = time.process_time(), time.perf_counter()
    func(*args, progress=progress)
    return {
        "cpu_s": time.process_time() - c0,
        "wall_s": time.perf_counter() - t0,
        "threads": numeric_threads(),
    }


def job_args(kind: str, csv_text: str, robot: str, model: str) -> tuple[Any, ...]:
    from comp_daemon.service import job_kinds

    if kind == "diagnosis":
        return job_kinds.diagnosis_job_args(csv_text, robot, 1)
    return job_kinds.fit_job_args(csv_text, robot, model, None, 1)


def in_process(kind: str, args: tuple[Any, ...]) -> dict[str, Any]:
    """The same function in this process (the command line's path)."""
    return timed_job(kind, args, progress=lambda *a, **k: None)


async def in_pool(
    kind: str, args: tuple[Any, ...], cpus: list[int], nice: int, threads: int
) -> dict[str, Any]:
    """The function as a job of the daemon's pool, the time from launch to its stored result."""
    from comp_daemon.service.config import JobSettings
    from comp_daemon.service.jobs import JobKind, JobRunner
    from comp_daemon.service.store import Store

    with tempfile.TemporaryDirectory() as tmp:
        store = Store(Path(tmp) / "s.sqlite3")
        settings = JobSettings(workers=1, nice=nice, cpus=cpus, threads=max(threads, 1))
        runner = JobRunner(store, settings)
        runner.register(JobKind("timed", timed_job))
        runner.start()
        try:
            job = store.create_job("timed", {})
            t0 = time.perf_counter()
            await asyncio.to_thread(runner.launch, job, (kind, args, threads == 0))
            while store.get_job(job.id).state in ("queued", "running"):
                await asyncio.sleep(0.05)
            await runner.drain()
            wall = time.perf_counter() - t0
            done = store.get_job(job.id)
            if done.state != "done":
                raise SystemExit(f"the job ended {done.state}: {done.message}")
            return {**dict(done.result or {}), "launch_to_stored_s": wall}
        finally:
            runner.shutdown()
            store.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--robot", required=True)
    ap.add_argument("--kind", choices=("diagnosis", "fit"), default="diagnosis")
    ap.add_argument("--model", default="kinematic+ratio+backlash")
    ap.add_argument("--cpus", default="0", help="CPUs of the worker, comma-separated ('' for every CPU)")
    ap.add_argument("--nice", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1, help="numeric threads of the worker; 0: default")
    ap.add_argument("--skip-cli", action="store_true")
    opts = ap.parse_args()
    set_numeric_threads(1)
    csv_text = Path(opts.data).read_text()
    args = job_args(opts.kind, csv_text, opts.robot, opts.model)
    cpus = [int(c) for c in opts.cpus.split(",") if c.strip()]
    print(machine_line())
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if not opts.skip_cli:
        cli = in_process(opts.kind, args)
        print(f"in process : wall {cli['wall_s']:.2f} s, CPU {cli['cpu_s']:.2f} s, threads {cli['threads']}")
    job = asyncio.run(in_pool(opts.kind, args, cpus, opts.nice, opts.threads))
    print(
        f"as a job   : wall {job['wall_s']:.2f} s in the worker, {job['launch_to_stored_s']:.2f} s launch to "
        f"stored, CPU {job['cpu_s']:.2f} s, threads {job['threads']} (cpus {cpus or 'all'}, nice {opts.nice})"
    )
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
