"""The HTTP service under readers and small writers, in a process of its own: memory and latency.

Measures, against the service alone (no daemon) serving a store filled beforehand (the data sets
and an active model with a 3 MB artifact, as a kriging model's):

1. ``lists``: the server's resident memory (RSS, and its peak VmHWM) around 10 parallel
   ``GET /api/datasets`` over ``--datasets`` data sets of ``--dataset-mb`` MB each;
2. ``downloads``: RSS with 30 clients that ask for a 20 MB data set and stop reading, then again
   after the server's write time limit (``http.write_timeout_s``, 30 s) has passed;
3. ``status``: with 50 clients (two processes of 25) polling ``/api/status`` without pause for
   ``--seconds``, the latencies (p50, p99) of a probe of ``/api/status`` and one of ``/health``
   every 50 ms from this process, and the server's CPU time per request;
4. ``uploads``: the share of 503 answers when 20 and then 50 clients each upload an 80 KB campaign
   at once;
5. ``upload``: the time from sending a 19.9 MB CSV to its 201.

``--src`` runs the server from another checkout (to compare with an older tree); the clients are
this one's. Run: ``python -m benchmarks.http_readers [--src PATH]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from benchmarks.machine import machine_line
from tests.test_service_hostile import big_csv  # a valid KR210 campaign of a given size

TOKEN = "bench-engineer-token-0123456789abcdef"
HEADERS = {"Authorization": f"Bearer {TOKEN}"}
MB = 1 << 20

_SERVER = """
import asyncio, json, sys
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import load_settings
from comp_daemon.service.http_server import build_http_server

async def main():
    s = load_settings(None, **json.loads(sys.argv[1]))
    store = open_store(s)
    server = build_http_server(create_app(s, store), s.http)
    print(server.port, flush=True)
    await server.serve()

if __name__ == "__main__":
    asyncio.run(main())
"""


def _settings(data_dir: Path) -> dict[str, Any]:
    return {
        "store": {"data_dir": str(data_dir)},
        "http": {"port": 0, "max_connections": 512},
        "auth": {"tokens": [{"name": "bench", "role": "engineer", "token": TOKEN}]},
    }


#: clients in a process of their own, each polling /api/status without pause; prints the answers
_POLLERS = """
import asyncio, sys, time
import httpx

async def main(url, token, clients, seconds):
    until = time.monotonic() + seconds
    done = 0
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=limits,
                                 headers={"Authorization": f"Bearer {token}"}) as c:
        async def poll():
            nonlocal done
            while time.monotonic() < until:
                await c.get("/api/status")
                done += 1
        await asyncio.gather(*(poll() for _ in range(clients)))
    print(done)

asyncio.run(main(sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])))
"""


def _memory_kb(pid: int) -> tuple[int, int]:
    """(VmRSS, VmHWM) of a process, in kB."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0])
    return fields["VmRSS"], fields["VmHWM"]


def _cpu_s(pid: int) -> float:
    """CPU time (user + system) a process has used, in seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _fill(src: Path, data_dir: Path, count: int, size_mb: float) -> list[int]:
    """Data sets of ``size_mb`` MB each, written by the tree under test's own store."""
    script = (
        "import hashlib, json, sys\n"
        "from comp_daemon.service.api import open_store\n"
        "from comp_daemon.service.config import load_settings\n"
        "s = load_settings(None, **json.loads(sys.argv[1]))\n"
        "store = open_store(s)\n"
        "ids = []\n"
        "for i, size in enumerate(json.loads(sys.argv[2])):\n"
        "    line = f'{i},0.1,0.2,0.3,0.4,0.5,0.6,1.5,2.5,3.5\\n'\n"
        "    text = 'n,a1,a2,a3,a4,a5,a6,x,y,z\\n' + line * (size // len(line))\n"
        "    ids.append(store.add_dataset(name=f'set-{i}', format='csv', content=text,\n"
        "        sha256=hashlib.sha256(text.encode()).hexdigest(), rows=text.count('\\n') - 1,\n"
        "        summary={'rows': text.count('\\n') - 1}).id)\n"
        "from comp_daemon.service.store import ModelDraft\n"
        "artifact = {'points': [[i * 0.001] * 9 for i in range(20000)]}\n"
        "model = store.add_model(ModelDraft(kind='kriging', order=None, artifact=artifact,\n"
        "    stats={'table2': {}}, dataset_id=ids[0]))\n"
        "store.activate_model(model.id)\n"
        "print(json.dumps(ids))\n"
    )
    sizes = [int(size_mb * MB)] * count + [20 * MB]
    out = subprocess.run(
        [sys.executable, "-c", script, json.dumps(_settings(data_dir)), json.dumps(sizes)],
        check=True,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(src)},
        cwd=src,  # "python -c" puts the working folder first on the path
    )
    ids: list[int] = json.loads(out.stdout)
    return ids


def _percentiles(values: list[float]) -> str:
    ordered = sorted(values)
    p99 = ordered[int(0.99 * (len(ordered) - 1))]
    return f"p50 {statistics.median(ordered) * 1e3:.0f} ms, p99 {p99 * 1e3:.0f} ms"


def _stalled(port: int, path: str) -> socket.socket:
    """A client that asks for ``path``, reads the first bytes of the answer and never reads again."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: cell\r\nAuthorization: Bearer {TOKEN}\r\n\r\n".encode())
    sock.recv(512)
    return sock


async def run(src: Path, datasets: int, dataset_mb: float, seconds: float) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = Path(tmp) / "data"
        ids = _fill(src, data_dir, datasets, dataset_mb)
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", _SERVER, json.dumps(_settings(data_dir)),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": str(src)}, cwd=src,
        )  # fmt: skip
        assert proc.stdout is not None
        port = int(await asyncio.wait_for(proc.stdout.readline(), 60))
        url = f"http://127.0.0.1:{port}"
        limits = httpx.Limits(max_connections=100, max_keepalive_connections=100)
        try:
            async with httpx.AsyncClient(base_url=url, headers=HEADERS, timeout=120, limits=limits) as c:
                await c.get("/api/status")
                rss0, _ = _memory_kb(proc.pid)
                await asyncio.gather(*(c.get("/api/datasets") for _ in range(10)))
                rss1, hwm1 = _memory_kb(proc.pid)
                print(
                    f"lists: {datasets} data sets of {dataset_mb:g} MB, 10 parallel GET /api/datasets: "
                    f"RSS {rss0 / 1024:.0f} -> {rss1 / 1024:.0f} MB (peak {hwm1 / 1024:.0f} MB)"
                )

                big = ids[-1]
                conns = [_stalled(port, f"/api/datasets/{big}/content") for _ in range(30)]
                await asyncio.sleep(2.0)
                rss2, _ = _memory_kb(proc.pid)
                await asyncio.sleep(33.0)
                rss3, _ = _memory_kb(proc.pid)
                for sock in conns:
                    sock.close()
                print(
                    f"downloads: 30 unread 20 MB downloads: RSS {rss1 / 1024:.0f} -> {rss2 / 1024:.0f} MB "
                    f"after 2 s, {rss3 / 1024:.0f} MB after 35 s"
                )

                status: list[float] = []
                health: list[float] = []
                until = 0.0

                async def probe(path: str, into: list[float]) -> None:
                    while time.monotonic() < until:
                        t0 = time.perf_counter()
                        r = await c.get(path)
                        into.append(time.perf_counter() - t0)
                        assert r.status_code == 200, r.text
                        await asyncio.sleep(0.05)

                cpu0 = _cpu_s(proc.pid)
                load = [
                    await asyncio.create_subprocess_exec(
                        sys.executable,
                        "-c",
                        _POLLERS,
                        url,
                        TOKEN,
                        "25",
                        str(seconds),
                        stdout=asyncio.subprocess.PIPE,
                    )
                    for _ in range(2)
                ]
                await asyncio.sleep(2.0)  # the pollers start (imports) before the probes do
                until = time.monotonic() + seconds - 3.0  # and end after them
                await asyncio.gather(probe("/api/status", status), probe("/health", health))
                polled = sum([int((await p.communicate())[0]) for p in load])
                cpu = (_cpu_s(proc.pid) - cpu0) / (polled + len(status) + len(health))
                print(f"status: 50 clients polling /api/status answered {polled} in {seconds:g} s")
                print(f"status: a probe meanwhile: /api/status {_percentiles(status)}")
                print(f"status: a probe meanwhile: /health {_percentiles(health)}")
                print(f"status: server CPU per request {cpu * 1e3:.1f} ms")

                small = big_csv(80_000)
                for clients in (20, 50):
                    answers = await asyncio.gather(
                        *(
                            c.post(
                                f"/api/datasets?name=small-{clients}-{i}",
                                content=small,
                                headers={"Content-Type": "text/csv"},
                            )
                            for i in range(clients)
                        )
                    )
                    busy = sum(r.status_code == 503 for r in answers)
                    other = sorted({r.status_code for r in answers} - {201, 503})
                    share = f"{busy} answered 503 ({busy / clients:.0%})"
                    print(f"uploads: {clients} x 80 KB at once: {share}, other answers {other}")

                body = big_csv(19_900_000)
                t0 = time.perf_counter()
                r = await c.post("/api/datasets?name=big", content=body, headers={"Content-Type": "text/csv"})
                took = time.perf_counter() - t0
                print(f"upload: {len(body) / 1e6:.1f} MB CSV: {r.status_code} in {took:.1f} s")
        finally:
            proc.terminate()
            await proc.wait()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--src", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--datasets", type=int, default=30)
    parser.add_argument("--dataset-mb", type=float, default=4.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args(argv)
    print(f"machine: {machine_line()}")
    print(f"server tree: {args.src}; load average {os.getloadavg()[0]:.1f}")
    asyncio.run(run(args.src.resolve(), args.datasets, args.dataset_mb, args.seconds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
