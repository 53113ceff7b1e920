"""Sim-to-real gap diagnosis (``docs/diagnosis-output.md``): the ladder, effect selection, where, report.

Modules, lowest first: ``fitting`` and ``stats`` (the numerics), ``result`` (options, steps and the
document), ``candidates`` (the effect catalogue as selection candidates), ``selection``, ``where``,
``ladder`` (:func:`diagnose`), ``plots`` and ``report`` (the HTML page).
"""

from comp_daemon.diagnosis.ladder import DiagnoseOptions, Diagnosis, Step, diagnose

__all__ = ["DiagnoseOptions", "Diagnosis", "Step", "diagnose"]
