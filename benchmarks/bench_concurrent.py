"""Several ``comp-daemon`` commands side by side, as on a shared machine: the wall and CPU time of
each (the children's own resource use), one alone first, and the load average.

``python -m benchmarks.bench_concurrent --copies 3 -- diagnose CAMPAIGN.csv --robot kr210 --json /dev/null``

``--control`` runs, instead of a command, a fixed NumPy and Python workload of this module
(:data:`CONTROL`: QR solves of a 2 100 × 60 matrix, a Python loop, dict building; about as much
CPU alone as a diagnosis of 1 000 poses × 3 targets): the same comparison for work that is not the
project's, i.e. what running side by side costs on this machine by itself (caches shared with the
other processes, context switches).

``--profile DIR`` runs each command under cProfile timed in CPU seconds (the one alone to
``DIR/alone.prof``, the copies to ``DIR/copy-N.prof``) and prints, for the functions that took the
most CPU alone, their own CPU in the copies against alone: whether the extra CPU of running side by
side is spread evenly (the machine: caches, time slices) or sits in some of the work.

``--inherit-threads`` starts the commands with the numeric libraries' thread variables removed from
their environment and ``--threads`` left out, so that a command line which does not set them (as
before it did) runs with the libraries' default, a thread per core; ``--pythonpath`` runs another
checkout of the code (before/after on the same machine).
"""

from __future__ import annotations

import argparse
import os
import pstats
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
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


#: ``python -c PROFILED OUT.prof ARGS…``: ``comp-daemon ARGS…`` under cProfile in CPU seconds
PROFILED = """
import cProfile, runpy, sys, time
out = sys.argv[1]
sys.argv = ["comp-daemon", *sys.argv[2:]]
prof = cProfile.Profile(time.process_time)
prof.enable()
try:
    runpy.run_module("comp_daemon", run_name="__main__", alter_sys=True)
finally:
    prof.disable()
    prof.dump_stats(out)
"""


def run_side_by_side(
    argv_of: Callable[[int], list[str]], copies: int, env: dict[str, str]
) -> list[dict[str, float]]:
    """Start ``copies`` commands at once, copy i's ``argv_of(i)``; each one's wall and CPU time."""
    t0 = time.perf_counter()
    argv = argv_of(0)
    procs = {
        subprocess.Popen(
            argv_of(i),
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
        "--profile", type=Path, default=None, metavar="DIR", help="cProfile each command (CPU time)"
    )
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
    if opts.control and opts.profile is not None:
        raise SystemExit("--profile profiles a comp-daemon command, not --control")
    command = (
        [sys.executable, "-c", CONTROL] if opts.control else [sys.executable, "-m", "comp_daemon", *argv]
    )

    def argv_of(name: str) -> Callable[[int], list[str]]:
        if opts.profile is None:
            return lambda i: command
        opts.profile.mkdir(parents=True, exist_ok=True)
        return lambda i: [sys.executable, "-c", PROFILED, str(opts.profile / name.format(i + 1)), *argv]

    load0 = os.getloadavg()
    alone = run_side_by_side(argv_of("alone.prof"), 1, env)[0]
    print(f"alone      : wall {alone['wall_s']:.2f} s, CPU {alone['cpu_s']:.2f} s (load {load0[0]:.2f})")
    load1 = os.getloadavg()
    many = run_side_by_side(argv_of("copy-{}.prof"), opts.copies, env)
    load2 = os.getloadavg()
    for i, r in enumerate(many):
        print(
            f"copy {i + 1} of {opts.copies}: wall {r['wall_s']:.2f} s, CPU {r['cpu_s']:.2f} s "
            f"({r['cpu_s'] / alone['cpu_s']:.2f} x alone)"
        )
    print(f"load average before / after the {opts.copies} copies: {load1[0]:.2f} / {load2[0]:.2f}")
    if opts.profile is not None:
        compare_profiles(
            opts.profile / "alone.prof", [opts.profile / f"copy-{i + 1}.prof" for i in range(opts.copies)]
        )


def own_cpu(path: Path) -> dict[str, float]:
    """Each function's own CPU seconds in a cProfile file, by a readable name."""
    table: Any = pstats.Stats(str(path)).stats  # type: ignore[attr-defined]
    out: dict[str, float] = {}
    for (file, line, name), (_cc, _nc, tottime, _ct, _callers) in table.items():
        key = f"{Path(file).name}:{line}({name})" if line else name
        out[key] = out.get(key, 0.0) + tottime
    return out


def compare_profiles(alone_path: Path, copy_paths: list[Path], top: int = 15) -> None:
    """The functions that took the most CPU alone: their own CPU in the copies against alone."""
    alone = own_cpu(alone_path)
    copies = [own_cpu(p) for p in copy_paths]
    total = sum(alone.values())
    print(
        f"profiled CPU alone {total:.2f} s; copies " + ", ".join(f"{sum(c.values()):.2f} s" for c in copies)
    )
    print("own CPU alone → in each copy (× alone), the costliest functions alone:")
    for key, t in sorted(alone.items(), key=lambda kv: -kv[1])[:top]:
        ratios = " / ".join(f"{c.get(key, 0.0) / t:.2f}" for c in copies)
        print(f"  {t:6.3f} s ({100 * t / total:4.1f} %) → {ratios} × {key}")


if __name__ == "__main__":
    main()
