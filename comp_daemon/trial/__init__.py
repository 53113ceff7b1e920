"""Seed 000's experiment end to end through the running daemon (``comp-daemon trial``, docs/trial.md).

Modules: :mod:`~comp_daemon.trial.plan` (the poses), :mod:`~comp_daemon.trial.cell` (the simulated
cell and the daemon as processes, and the trial's clients), :mod:`~comp_daemon.trial.runner` (the
phases), :mod:`~comp_daemon.trial.stats` (ISO 9283, histograms), :mod:`~comp_daemon.trial.compare`
(seed 001's model comparison), :mod:`~comp_daemon.trial.verdict`, :mod:`~comp_daemon.trial.report`
(text and HTML), :mod:`~comp_daemon.trial.result` (the JSON document). Units: mm in the robot base
frame, deg in the controller's axis convention.
"""

from comp_daemon.trial.plan import FULL, QUICK, TrialPlan, TrialSizes
from comp_daemon.trial.result import PointRun, TrialResult
from comp_daemon.trial.runner import ProgressEvent, TrialError, run_trial

__all__ = [
    "FULL",
    "QUICK",
    "PointRun",
    "ProgressEvent",
    "TrialError",
    "TrialPlan",
    "TrialResult",
    "TrialSizes",
    "run_trial",
]
