"""RSI codec cost per telegram: parse a full KR C4 ``<Rob>`` telegram, build the ``<Sen>`` reply.

Run: ``python -m benchmarks.bench_rsi_codec`` (``--n`` telegrams per repeat, ``--repeats``).
Reports microseconds per telegram (best and median over the repeats) for parse, build and both.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import statistics
import time
from collections.abc import Callable

from benchmarks.machine import machine_info, machine_line
from comp_daemon.rt.rsi_codec import SenReply, build_rob, build_sen, parse_rob


def _telegrams(n: int) -> list[bytes]:
    """Distinct realistic telegrams (RIst, RSol, AIPos, ASPos, Delay, IPOC; 4 decimals like a KR C4)."""
    out = []
    for k in range(n):
        a = (0.001 * k, -90.0 + 1e-4 * k, 90.0, 0.5, 45.0 - 1e-4 * k, 12.25)
        x = (1445.1234 + 0.01 * k, -12.5, 1890.0, 179.9, 0.1, -179.8)
        out.append(build_rob(5_490_270 + 12 * k, a, a, x, x, 0))
    return out


def _per_item_us(fn: Callable[[], None], n: int, repeats: int) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        times.append((time.perf_counter_ns() - t0) / n / 1000.0)
    return min(times), statistics.median(times)


def run(n: int, repeats: int) -> dict[str, object]:
    datagrams = _telegrams(n)
    telegrams = [parse_rob(d) for d in datagrams]
    replies = [SenReply(t.ipoc, (0.002, -0.001, 0.0005, 0.0, 0.0, 0.0)) for t in telegrams]

    def parse_all() -> None:
        for d in datagrams:
            parse_rob(d)

    def build_all() -> None:
        for r in replies:
            build_sen(r)

    def both() -> None:
        for d in datagrams:
            t = parse_rob(d)
            build_sen(SenReply(t.ipoc, (0.002, -0.001, 0.0005, 0.0, 0.0, 0.0)))

    both()  # warm-up
    parse_best, parse_median = _per_item_us(parse_all, n, repeats)
    build_best, build_median = _per_item_us(build_all, n, repeats)
    both_best, both_median = _per_item_us(both, n, repeats)
    return {
        "benchmark": "rsi_codec_parse_build",
        "telegram_bytes": len(datagrams[0]),
        "telegrams_per_repeat": n,
        "repeats": repeats,
        "parse_us": {"best": round(parse_best, 2), "median": round(parse_median, 2)},
        "build_us": {"best": round(build_best, 2), "median": round(build_median, 2)},
        "parse_plus_build_us": {"best": round(both_best, 2), "median": round(both_median, 2)},
        "date": dt.date.today().isoformat(),
        "machine": machine_info(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=10_000, help="telegrams per repeat")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    result = run(args.n, args.repeats)
    pb = result["parse_plus_build_us"]
    assert isinstance(pb, dict)
    print(
        f"RSI codec, {result['telegram_bytes']}-byte telegram: parse {result['parse_us']} µs, "
        f"build {result['build_us']} µs, parse+build best {pb['best']} µs / median {pb['median']} µs "
        f"per telegram on {machine_line()}"
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
