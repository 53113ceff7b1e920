"""The reduced trial (``comp-daemon trial --quick``) through the running daemon: a test of behaviour.

The simulated cell and ``comp-daemon run`` come up as processes; the trial calibrates the gratings
over HTTP, runs ISO 9283 with and without joint feedback, samples, fits over HTTP, and runs the
target points uncompensated, with kinematic calibration, and with the Chebyshev model and the
joint loop. Checked: the ordering of seed 000's Table 2 (closed loop beats kinematic calibration
beats uncompensated, in 3-D mean and max), the joint loop shrinking the multi-directional pose
accuracy variation, every daemon target done, the server's fit equal to the same fit made locally,
and a clean stop of the daemon. No absolute number is asserted.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.trial.plan import QUICK, TrialPlan
from comp_daemon.trial.report import render_html, render_text
from comp_daemon.trial.result import TrialResult
from comp_daemon.trial.runner import ProgressEvent, run_trial
from comp_daemon.trial.verdict import verdict

pytestmark = [pytest.mark.slow, pytest.mark.timeout(400)]


async def test_quick_trial_orders_the_methods_like_seed_000(tmp_path: Path) -> None:
    events: list[ProgressEvent] = []
    result = await run_trial(TrialPlan(sizes=QUICK), tmp_path / "work", progress=events.append)
    assert result.complete and result.error is None

    # the ordering of seed 000's Table 2
    v = verdict(result)
    assert v["ordering"]["mean"] and v["ordering"]["max"], render_text(result)
    t2 = result.table2()
    assert set(t2) == {"uncompensated", "kinematic", "chebyshev+feedback", "chebyshev-seed000+feedback"}
    assert all(st["n"] == QUICK.n_targets for st in t2.values())
    for key in ("chebyshev+feedback", "chebyshev-seed000+feedback"):
        loop_run = result.runs[key]
        assert loop_run.feedback and loop_run.failures() == [] and set(loop_run.state) == {"done"}
        assert np.all(np.isfinite(loop_run.grating_deg))
    # seed 000's mapping moves joints 1-3 only: the wrist is commanded at its nominal axis values,
    # where the six-axis mapping turns it
    seed000 = result.runs["chebyshev-seed000+feedback"].commanded_deg
    six = result.runs["chebyshev+feedback"].commanded_deg
    nominal = result.runs["uncompensated"].commanded_deg
    np.testing.assert_allclose(seed000[:, 3:], nominal[:, 3:], atol=1e-6)
    assert np.abs(seed000[:, :3] - nominal[:, :3]).max() > 1e-3
    assert np.abs(six[:, 3:] - nominal[:, 3:]).max() > 1e-3

    # ISO 9283: the joint loop removes the joint 1-3 share of the direction-dependent error
    iso = result.iso["runs"]
    assert iso["with"]["failed"] == []
    assert iso["with"]["stats"]["vap_mm"][0] < iso["without"]["stats"]["vap_mm"][0]

    # the gratings were calibrated over HTTP: three poses, each from both sides
    assert result.gratings is not None and result.gratings["version"] == 1
    assert [m["joint"] for m in result.gratings["joints"]] == [1, 2, 3]
    assert all(m["n_readings"] == 6 for m in result.gratings["joints"])

    # data sets and fits over HTTP; the server's kinematic fit is the one the library makes
    assert set(result.datasets) == {"trial-open-loop", "trial-open-loop-gratings"}
    assert result.datasets["trial-open-loop"]["fit_rows"] == QUICK.n_sampling
    assert set(result.models) == {"nominal", "kinematic", "chebyshev"}
    server = result.models["kinematic"]["server_table2"]["model"]["3d"]
    local = result.comparison["open"]["models"]["kinematic"]["table2"]["3d"]
    assert server["mean"] == pytest.approx(local["mean"], abs=1e-6)
    assert server["max"] == pytest.approx(local["max"], abs=1e-6)

    # the daemon ran the loop and stopped cleanly
    assert result.loop["daemon_exit_code"] == 0
    assert result.loop["controller"]["state"] == "running"  # RSI never stopped during the trial
    iso_targets = len(QUICK.iso_fractions) * 3 * (QUICK.iso_cycles + QUICK.iso_warmup_cycles)
    assert result.loop["targets"]["done"] == iso_targets + 2 * QUICK.n_targets

    # progress was reported for every phase, the result survives JSON, the reports render
    assert {e.phase for e in events if e.finished} >= {"grating calibration", "seed 001 model comparison"}
    back = TrialResult.from_dict(json.loads(result.to_json()))
    assert back.table2()["chebyshev+feedback"]["3d"] == pytest.approx(t2["chebyshev+feedback"]["3d"])
    assert "Table 2" in render_text(back)
    assert "<svg" in render_html(back)
