"""Several ``comp-daemon`` commands side by side, as on a shared machine: the wall and CPU time of
each (the children's own resource use), one alone first, and the load average.

``python -m benchmarks.bench_concurrent --copies 3 -- diagnose CAMPAIGN.csv --robot kr210 --json /dev/null``

``--control`` runs, instead of a command, a fixed NumPy and Python workload of this module
(:data:`CONTROL`: QR solves of a 2 100 × 60 matrix, a Python loop, dict building; about as much
CPU alone as a diagnosis of 1 000 poses × 3 targets): the same comparison for work that is not the
project's, i.e. what running side by side costs on this machine by itself (caches shared with the
other processes, context switches).

``--inherit-threads`` starts the commands with the numeric libraries' thread variables removed from
their environment and ``--threads`` left out, so that a command line which does not set them (as
before it did) runs with the libraries' default, a thread per core; ``--pythonpath`` runs another
checkout of the code (before/after on the same machine).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from typing import Any

from benchmarks.machine import machine_line
from comp_daemon.common.threads import THREAD_VARIABLES

#: the control workload (``--control``), NumPy at the thread count the environment sets
CONTROL = """
import numpy as np
rng = np.random.default_rng(0)
a = rng.standard_normal((2100, 60))
b = rng.standard_normal(2100)
s = 0.0
for i in range(1300):
    q, r = np.linalg.qr(a)
    s += float(np.linalg.solve(r, q.T @ b)[0])
    s += sum(float(x) for x in a[i % 2100, :])
    d = {k: k * 2 for k in range(3000)}
"""


def run_side_by_side(argv: list[str], copies: int, env: dict[str, str]) -> list[dict[str, float]]:
    """Start ``copies`` of ``ARGV`` at once; each one's wall and CPU time."""
    t0 = time.perf_counter()
    procs = {
        subprocess.Popen(
            argv,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        ).pid: i
        for i in range(copies)
    }
    out: list[dict[str, float]] = [{} for _ in range(copies)]
    while procs:
        pid, status, usage = os.wait4(-1, 0)
        if pid not in procs:
            continue
        i = procs.pop(pid)
        if os.waitstatus_to_exitcode(status) != 0:
            code = os.waitstatus_to_exitcode(status)
            raise SystemExit(f"copy {i} of {' '.join(argv)[:200]} failed ({code})")
        out[i] = {"wall_s": time.perf_counter() - t0, "cpu_s": usage.ru_utime + usage.ru_stime}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--copies", type=int, default=3)
    ap.add_argument("--inherit-threads", action="store_true")
    ap.add_argument("--control", action="store_true", help="the control workload instead of a command")
    ap.add_argument("--pythonpath", default=None)
    ap.add_argument(
        "argv", nargs=argparse.REMAINDER, help="-- then the comp-daemon command and its arguments"
    )
    opts = ap.parse_args()
    argv = [a for a in opts.argv if a != "--"] if opts.argv[:1] == ["--"] else list(opts.argv)
    if not argv and not opts.control:
        raise SystemExit("name the command after -- (or --control)")
    env: dict[str, Any] = dict(os.environ)
    if opts.pythonpath:
        env["PYTHONPATH"] = opts.pythonpath
    if opts.inherit_threads:
        for name in (*THREAD_VARIABLES, "COMP_DAEMON_THREADS"):
            env.pop(name, None)
    print(machine_line())
    print(
        ("command: the control workload" if opts.control else f"command: comp-daemon {' '.join(argv)}")
        + (" (library default threads)" if opts.inherit_threads else "")
    )
    argv = [sys.executable, "-c", CONTROL] if opts.control else [sys.executable, "-m", "comp_daemon", *argv]
    load0 = os.getloadavg()
    alone = run_side_by_side(argv, 1, env)[0]
    print(f"alone      : wall {alone['wall_s']:.2f} s, CPU {alone['cpu_s']:.2f} s (load {load0[0]:.2f})")
    load1 = os.getloadavg()
    many = run_side_by_side(argv, opts.copies, env)
    load2 = os.getloadavg()
    for i, r in enumerate(many):
        print(
            f"copy {i + 1} of {opts.copies}: wall {r['wall_s']:.2f} s, CPU {r['cpu_s']:.2f} s "
            f"({r['cpu_s'] / alone['cpu_s']:.2f} x alone)"
        )
    print(f"load average before / after the {opts.copies} copies: {load1[0]:.2f} / {load2[0]:.2f}")


if __name__ == "__main__":
    main()
