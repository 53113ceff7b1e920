"""Job worker processes: a cancelled job that never reports is stopped by killing its worker, the
other jobs of the pool are started again, and workers end with the daemon (also after kill -9)."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest

from comp_daemon.service.config import JobSettings
from comp_daemon.service.jobs import JobKind, JobRunner
from comp_daemon.service.store import JobRecord, Store

# ---- job functions: module level, so that worker processes can import them


def deaf(seconds: float, *, progress: Callable[..., None]) -> dict[str, Any]:
    """A long computation that never reports progress (so never sees a cancellation)."""
    progress(0.0, f"pid {os.getpid()}")
    time.sleep(seconds)
    return {"slept": seconds}


def quick(value: int, *, progress: Callable[..., None]) -> dict[str, Any]:
    return {"value": value, "pid": os.getpid()}


def steady(seconds: float, *, progress: Callable[..., None]) -> dict[str, Any]:
    progress(0.0, f"pid {os.getpid()}")
    time.sleep(seconds)
    return {"slept": seconds, "pid": os.getpid()}


def attentive(seconds: float, *, progress: Callable[..., None]) -> dict[str, Any]:
    """Reports progress every 10 ms (so stops at once when cancelled)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        progress(0.5, f"pid {os.getpid()}")
        time.sleep(0.01)
    return {"spun": seconds}


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie has ended, only its parent has not reaped it
        return f.read().rsplit(")", 1)[1].split()[0] != "Z"


async def until(cond: Callable[[], bool], limit_s: float = 30.0) -> None:
    deadline = time.monotonic() + limit_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.05)


def worker_pid(store: Store, job: JobRecord) -> int | None:
    message = store.get_job(job.id).message or ""
    return int(message.split()[1]) if message.startswith("pid ") else None


@pytest.fixture
async def runner(tmp_path: Path) -> AsyncIterator[tuple[JobRunner, Store]]:
    store = Store(tmp_path / "s.sqlite3")
    runner = JobRunner(store, JobSettings(workers=2, cancel_grace_s=0.5))
    for kind in (JobKind("deaf", deaf), JobKind("quick", quick), JobKind("steady", steady)):
        runner.register(kind)
    runner.start()
    yield runner, store
    await runner.drain()
    runner.shutdown()
    store.close()


async def test_cancelling_a_job_that_never_reports_kills_its_worker(runner: Any) -> None:
    runner, store = runner
    job = store.create_job("deaf", {})
    await asyncio.to_thread(runner.launch, job, (120.0,))
    await until(lambda: worker_pid(store, job) is not None)
    pid = worker_pid(store, job)
    assert pid is not None
    other = store.create_job("steady", {})  # shares the pool: lost with the killed worker, redone
    await asyncio.to_thread(runner.launch, other, (1.5,))
    await until(lambda: worker_pid(store, other) is not None)
    first_pid = worker_pid(store, other)

    t0 = time.monotonic()
    assert runner.cancel(job.id, by="test").state == "cancelled"
    await until(lambda: not alive(pid), 10.0)
    assert time.monotonic() - t0 < 3.0  # the grace (0.5 s) and the pool noticing, not 120 s

    await until(lambda: store.get_job(other.id).state in ("done", "failed"), 60.0)
    redone = store.get_job(other.id)
    assert redone.state == "done", redone.error
    assert redone.result is not None and redone.result["pid"] != first_pid  # it ran again, elsewhere
    assert store.get_job(job.id).state == "cancelled" and store.get_job(job.id).result is None

    after = store.create_job("quick", {})  # the renewed pool takes new work
    await asyncio.to_thread(runner.launch, after, (7,))
    await until(lambda: store.get_job(after.id).state in ("done", "failed"), 60.0)
    assert store.get_job(after.id).result == {"value": 7, "pid": store.get_job(after.id).result["pid"]}


async def test_a_job_that_stops_when_asked_keeps_its_worker(runner: Any) -> None:
    runner, store = runner
    runner.register(JobKind("attentive", attentive))
    job = store.create_job("attentive", {})
    await asyncio.to_thread(runner.launch, job, (60.0,))
    await until(lambda: (store.get_job(job.id).message or "").startswith("pid "))
    pid = int((store.get_job(job.id).message or "").split()[1])
    runner.cancel(job.id, by="test")
    await asyncio.sleep(1.5)  # past the grace
    await runner.drain()
    assert alive(pid) and store.get_job(job.id).state == "cancelled"


_DAEMON = """
import asyncio, sys
from comp_daemon.service.config import JobSettings
from comp_daemon.service.jobs import JobKind, JobRunner
from comp_daemon.service.store import Store
sys.path.insert(0, sys.argv[2])
from test_service_job_workers import deaf

async def main():
    store = Store(sys.argv[1])
    runner = JobRunner(store, JobSettings(workers=1))
    runner.register(JobKind("deaf", deaf))
    runner.start()
    job = store.create_job("deaf", {})
    await asyncio.to_thread(runner.launch, job, (600.0,))
    while not (store.get_job(job.id).message or "").startswith("pid "):
        await asyncio.sleep(0.05)
    print(store.get_job(job.id).message.split()[1], flush=True)
    await asyncio.sleep(600)

asyncio.run(main())
"""


def test_workers_end_when_the_daemon_is_killed(tmp_path: Path) -> None:
    daemon = subprocess.Popen(
        [sys.executable, "-c", _DAEMON, str(tmp_path / "s.sqlite3"), str(Path(__file__).parent)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert daemon.stdout is not None
        worker = int(daemon.stdout.readline())
        assert alive(worker)
        os.kill(daemon.pid, signal.SIGKILL)
        daemon.wait(10)
        deadline = time.monotonic() + 5.0
        while alive(worker) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(worker), "the worker outlived the daemon"
    finally:
        if daemon.poll() is None:
            daemon.kill()
        daemon.wait(10)
        if daemon.stdout is not None:
            daemon.stdout.close()


async def test_a_pool_broken_under_cancelled_waiting_jobs_still_takes_work(tmp_path: Path) -> None:
    """One worker busy with a deaf job, three jobs waiting behind it, the last cancelled; the deaf
    one is cancelled and its worker killed. The waiting jobs still wanted run in the new pool, the
    cancelled one never does, and later work completes."""
    store = Store(tmp_path / "s.sqlite3")
    runner = JobRunner(store, JobSettings(workers=1, cancel_grace_s=0.3))
    for kind in (JobKind("deaf", deaf), JobKind("quick", quick)):
        runner.register(kind)
    runner.start()
    try:
        busy = store.create_job("deaf", {})
        await asyncio.to_thread(runner.launch, busy, (120.0,))
        await until(lambda: worker_pid(store, busy) is not None)
        wanted = [store.create_job("quick", {}) for _ in range(2)]  # fill the pool's call queue
        for job in wanted:
            await asyncio.to_thread(runner.launch, job, (2,))
        dropped = store.create_job("quick", {})  # waits in the pool itself
        await asyncio.to_thread(runner.launch, dropped, (1,))
        runner.cancel(dropped.id, by="test")
        runner.cancel(busy.id, by="test")
        await until(lambda: all(store.get_job(j.id).state in ("done", "failed") for j in wanted), 60.0)
        assert [store.get_job(j.id).state for j in wanted] == ["done", "done"]
        assert store.get_job(dropped.id).state == "cancelled" and store.get_job(dropped.id).result is None
        later = store.create_job("quick", {})
        await asyncio.to_thread(runner.launch, later, (3,))
        await until(lambda: store.get_job(later.id).state in ("done", "failed"), 60.0)
        assert (store.get_job(later.id).result or {}).get("value") == 3
    finally:
        await runner.drain()
        runner.shutdown()
        store.close()
