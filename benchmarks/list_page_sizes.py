"""Bytes per fit in a page of ``/api/jobs`` or ``/api/models``: full statistics vs the list summary.

A list page decodes and serialises every row's statistics while holding the GIL, which the RSI
reply on the real-time thread waits for; lists therefore carry a summary (the store's
``json_remove`` of ``STATS_DETAIL_PATHS`` in SQL, then ``schemas.stats_summary``). This measures
both on fits of the campaign ``bench_rsi_loop`` uses (``kr210-cell``, 1 000 rows, seed 11).

Run: ``python -m benchmarks.list_page_sizes [--rows 1000]``
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.machine import machine_line
from comp_daemon.service.job_kinds import run_fit
from comp_daemon.service.schemas import stats_summary
from comp_daemon.service.store import without_details as _without_details

MODELS = ("chebyshev", "kinematic+ratio+backlash")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=1000, help="rows of the simulated campaign")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "campaign.csv"
        sample = ["sim", "sample", "--n", str(args.rows), "--out", str(csv), "--seed", "11"]
        subprocess.run([sys.executable, "-m", "comp_daemon", *sample], check=True, capture_output=True)
        text = csv.read_text(encoding="utf-8")
    print(f"machine: {machine_line()}")
    conn = sqlite3.connect(":memory:")
    for model in MODELS:
        stats = run_fit(text, "kr210", model, None, 1, progress=lambda *a, **k: None)["stats"]
        full = json.dumps(stats, separators=(",", ":"))
        stripped = conn.execute(f"SELECT {_without_details('?')}", (full,)).fetchone()[0]
        summary = json.dumps(stats_summary(json.loads(stripped)), separators=(",", ":"))
        print(
            f"{model}: full statistics {len(full)} B, after json_remove {len(stripped)} B, "
            f"list summary {len(summary)} B; a page of 100: {100 * len(full) / 1e6:.2f} MB → "
            f"{100 * len(summary) / 1e6:.2f} MB"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
