"""Sim-to-real gap diagnosis (``shared/spec/diagnose.md``): the ladder, effect selection, where, report."""

from comp_daemon.diagnosis.ladder import DiagnoseOptions, Diagnosis, Step, diagnose

__all__ = ["DiagnoseOptions", "Diagnosis", "Step", "diagnose"]
