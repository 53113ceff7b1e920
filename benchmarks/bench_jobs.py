"""A diagnosis and a fit as the daemon runs them (a job in its worker pool: a spawned, niced process
off the real-time CPU) against the same work in the command line's process, on the same data.

``python -m benchmarks.bench_jobs --data CAMPAIGN.csv --robot kr210 [--kind diagnosis|fit]
[--model NAME] [--cpus 0] [--nice 10] [--threads 1]``

Prints, for each path, the wall time and the CPU time of the process that did the work (the job's
worker measures its own), and the load average. ``--threads 0`` leaves the worker's numeric
libraries at their default (a thread per core), as the pool did before it set them.

``--http N`` compares the whole paths instead, N rounds alternated (the command line first in odd
rounds, the job first in even ones): the command (``comp-daemon fit DATA --robot R --model M --out
…``, or ``comp-daemon diagnose DATA --robot R --json … --report …``, which writes the HTML report a
diagnosis job renders too) in a child process, its wall and CPU time, against the job started by a
POST to the service (``/api/fits`` or ``/api/diagnoses``; the service in this process, its job
workers spawned with ``--cpus`` and ``--nice`` as ``jobs.cpus`` and ``jobs.nice``: by default on CPU
0 at nice 10, as ``comp-daemon run`` keeps them off the real-time CPU of a two-core machine; ``--cpus
''`` leaves them unpinned, as the service alone does), from the POST to the job's
state ``done``, and the CPU of the service's process and of its workers (from ``/proc``) meanwhile.
The data set is uploaded once, before the rounds; the first job also starts the pool's worker.
Round i fits with the folds' seed i in both paths (:data:`FIRST_SEED`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import secrets
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
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

    func: Callable[..., Any] = job_kinds.run_fit
    if kind == "diagnosis":
        func = job_kinds.run_diagnosis
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


#: the folds' seed of the first round; each round takes the next, in both paths, so that a job's
#: worker, which keeps the base fits it made (``fitting.selected_base``), does not serve a round
#: from an earlier one's
FIRST_SEED = 1


def descendants_cpu_s(root: int) -> dict[int, float]:
    """User + system CPU seconds of every live descendant of process ``root``, by pid (``/proc``)."""
    tick = os.sysconf("SC_CLK_TCK")
    parent: dict[int, int] = {}
    cpu: dict[int, float] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        parent[int(entry)] = int(fields[1])
        cpu[int(entry)] = (int(fields[11]) + int(fields[12])) / tick
    out = {}
    for pid in cpu:
        p = parent.get(pid, 0)
        while p > 1 and p != root:
            p = parent.get(p, 0)
        if p == root:
            out[pid] = cpu[pid]
    return out


def command_line(kind: str, data: str, robot: str, model: str, seed: int, tmp: Path) -> dict[str, float]:
    """The command line's whole path in a child process: its wall time and CPU time."""
    if kind == "fit":
        argv = ["fit", data, "--robot", robot, "--model", model, "--out", str(tmp / "model.json")]
    else:
        argv = ["diagnose", data, "--robot", robot, "--json", str(tmp / "d.json")]
        argv += ["--report", str(tmp / "d.html")]
    argv += ["--seed", str(seed)]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "comp_daemon", *argv], stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"comp-daemon {' '.join(argv)} failed ({proc.returncode})")
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime}


async def http_rounds(
    kind: str, data: Path, robot: str, model: str, rounds: int, jobs: dict[str, Any]
) -> list[dict[str, Any]]:
    """``rounds`` pairs of (command line, HTTP job), alternated; each path's wall and CPU time.
    ``jobs``: the service's job settings (``jobs.cpus``, ``jobs.nice``)."""
    import httpx

    from comp_daemon.service.api import create_app, open_store
    from comp_daemon.service.config import load_settings

    token = secrets.token_hex(16)
    headers = {"Authorization": f"Bearer {token}"}
    out: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        settings = load_settings(
            None,
            store={"data_dir": str(tmp / "data")},
            auth={"tokens": [{"name": "bench", "role": "engineer", "token": token}]},
            robot={"name": robot},
            jobs=jobs,
        )
        async with contextlib.AsyncExitStack() as stack:
            store = open_store(settings)
            stack.callback(store.close)
            app = create_app(settings, store)
            await stack.enter_async_context(app.router.lifespan_context(app))
            client = await stack.enter_async_context(
                httpx.AsyncClient(
                    transport=httpx.ASGITransport(app=app),
                    base_url="http://cell",
                    headers=headers,
                    timeout=60.0,
                )
            )
            t0 = time.perf_counter()
            up = await client.post(
                f"/api/datasets?name={data.stem}",
                content=data.read_bytes(),
                headers={"Content-Type": "text/csv"},
            )
            if up.status_code != 201:
                raise SystemExit(f"the upload was refused: {up.status_code} {up.text}")
            print(f"upload     : {time.perf_counter() - t0:.2f} s")
            dataset_id = int(up.json()["id"])
            for i in range(rounds):
                job_first = i % 2 == 1
                row: dict[str, Any] = {"job_first": job_first}
                for path in ("job", "cli") if job_first else ("cli", "job"):
                    if path == "cli":
                        row["cli"] = await asyncio.to_thread(
                            command_line, kind, str(data), robot, model, FIRST_SEED + i, tmp
                        )
                    else:
                        row["job"] = await http_job(client, kind, dataset_id, model, FIRST_SEED + i)
                row["load"] = os.getloadavg()[0]
                out.append(row)
                print(f"round {i + 1} {round_line(row)}")
    return out


def round_line(row: dict[str, Any]) -> str:
    cli, job = row["cli"], row["job"]
    return (
        f"({'job' if row['job_first'] else 'command line'} first): command line wall {cli['wall_s']:.2f} s "
        f"CPU {cli['cpu_s']:.2f} s; job wall {job['wall_s']:.2f} s CPU {job['cpu_s']:.2f} s (workers "
        f"{job['worker_cpu_s']:.2f} s, service {job['service_cpu_s']:.2f} s); load {row['load']:.2f}"
    )


async def http_job(client: Any, kind: str, dataset_id: int, model: str, seed: int) -> dict[str, float]:
    """One job through the service, from its POST to its state ``done``: wall and CPU time."""
    me = os.getpid()
    before = descendants_cpu_s(me)
    c0, t0 = time.process_time(), time.perf_counter()
    if kind == "fit":
        r = await client.post("/api/fits", json={"dataset_id": dataset_id, "model": model, "seed": seed})
    else:
        r = await client.post("/api/diagnoses", json={"dataset_id": dataset_id, "seed": seed})
    if r.status_code != 202:
        raise SystemExit(f"the job was refused: {r.status_code} {r.text}")
    job_id = int(r.json()["id"])
    while True:
        job = (await client.get(f"/api/jobs/{job_id}")).json()
        if job["state"] not in ("queued", "running"):
            break
        await asyncio.sleep(0.05)
    wall, service = time.perf_counter() - t0, time.process_time() - c0
    if job["state"] != "done":
        raise SystemExit(f"job {job_id} ended {job['state']}: {job.get('error')}")
    after = descendants_cpu_s(me)
    workers = sum(cpu - before.get(pid, 0.0) for pid, cpu in after.items())
    return {"wall_s": wall, "cpu_s": service + workers, "worker_cpu_s": workers, "service_cpu_s": service}


def http_main(opts: argparse.Namespace) -> None:
    print(machine_line())
    what = opts.model if opts.kind == "fit" else "diagnosis"
    print(f"{what} on {opts.data} ({opts.robot}): command line against an HTTP job, {opts.http} rounds")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    cpus = [int(c) for c in opts.cpus.split(",") if c.strip()]
    print(f"job workers: cpus {cpus or 'not pinned'}, nice {opts.nice}")
    jobs = {"cpus": cpus, "nice": opts.nice}
    rows = asyncio.run(http_rounds(opts.kind, Path(opts.data), opts.robot, opts.model, opts.http, jobs))
    warm = rows[1:] or rows  # the first job also starts the pool's worker
    for key in ("wall_s", "cpu_s"):
        ratios = [r["job"][key] / r["cli"][key] for r in warm]
        print(
            f"job / command line, {key[:-2]}: median {statistics.median(ratios):.2f} "
            f"(rounds {2 if len(rows) > 1 else 1}..{len(rows)}: {', '.join(f'{x:.2f}' for x in ratios)})"
        )
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


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
    ap.add_argument(
        "--http", type=int, default=0, metavar="N", help="N alternated rounds: command line against HTTP job"
    )
    opts = ap.parse_args()
    set_numeric_threads(1)
    if opts.http:
        http_main(opts)
        return
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
