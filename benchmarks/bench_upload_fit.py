"""A fit job right after an upload: the data set handed over as the upload parsed it against its
stored CSV text parsed again in the worker (the path a job takes when the service no longer holds
the parsed data set, e.g. after a restart).

``python -m benchmarks.bench_upload_fit [--rows 1000] [--repeat 20] [--model kinematic]``

The campaign is sampled by the simulator (``kr210-cell``, seed 3). Each path is timed from the
parent's pickling of the job's data argument to the data set ready in the worker (unpickling, and
for the text the parse): the median of ``--repeat`` runs in this process. Then the whole fit job
(:func:`comp_daemon.service.job_kinds.run_fit`) both ways, alternated, the median of three each.
"""

from __future__ import annotations

import argparse
import pickle
import statistics
import time
from pathlib import Path
from typing import Any

from benchmarks.machine import machine_line
from comp_daemon.data.dataset import parse_dataset
from comp_daemon.robot.description import load_robot
from comp_daemon.service.job_kinds import run_fit
from comp_daemon.service.uploads import ParsedDatasets, check_upload
from comp_daemon.sim.campaign import run_campaign
from comp_daemon.sim.scenario import load_scenario

SCENARIO = Path(__file__).resolve().parents[1] / "comp_daemon" / "sim" / "scenarios" / "kr210-cell.toml"


def _median_ms(work: Any, repeat: int) -> float:
    work()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        work()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--model", default="kinematic")
    opts = ap.parse_args()
    robot = load_robot("kr210")
    from comp_daemon.data.dataset import dataset_to_csv

    body = dataset_to_csv(run_campaign(load_scenario(str(SCENARIO)), opts.rows, seed=3)).encode()
    checked = check_upload(body, "csv", "campaign", robot.axis_limits_deg, "measurement")
    assert checked.dataset is not None
    kept = ParsedDatasets()
    kept.put(1, checked.dataset)
    parsed = kept.get(1, checked.sha256)
    assert parsed is not None
    text = checked.content

    def from_text() -> None:
        arrived = pickle.loads(pickle.dumps(text))
        parse_dataset(
            arrived, source="dataset 1", limits_deg=robot.axis_limits_deg, min_rows=1, kind="measurement"
        )

    def from_parsed() -> None:
        pickle.loads(pickle.dumps(parsed)).content_sha256  # noqa: B018 (the hash the fit takes)

    print(machine_line())
    print(
        f"{len(parsed)} rows, {len(text)} bytes of canonical CSV, {len(pickle.dumps(parsed))} bytes pickled"
    )
    old, new = _median_ms(from_text, opts.repeat), _median_ms(from_parsed, opts.repeat)
    print(
        f"data set ready in the worker: stored text parsed {old:.1f} ms, as the upload parsed it {new:.1f} ms"
    )

    def job(data: Any) -> float:
        t0 = time.perf_counter()
        run_fit(data, "kr210", opts.model, None, 1, progress=lambda *a, **k: None)
        return time.perf_counter() - t0

    job(parsed)  # imports and first-call costs out of the way
    runs: dict[str, list[float]] = {"text": [], "parsed": []}
    for _ in range(3):  # alternated: the machine's load falls on both alike
        runs["text"].append(job(text))
        runs["parsed"].append(job(parsed))
    whole = {k: statistics.median(v) for k, v in runs.items()}
    print(
        f"whole {opts.model} fit job (median of 3): from the text {whole['text']:.3f} s, "
        f"from the parsed data set {whole['parsed']:.3f} s"
    )


if __name__ == "__main__":
    main()
