"""The diagnosis's options of the settings both doors build
(:class:`comp_daemon.preparation.options.DiagnosisSettings`: ``comp-daemon diagnose``'s options and
the HTTP diagnosis request)."""

from __future__ import annotations

from comp_daemon.diagnosis.result import DiagnoseOptions
from comp_daemon.preparation.options import DiagnosisSettings

__all__ = ["diagnose_options"]


def diagnose_options(settings: DiagnosisSettings) -> DiagnoseOptions:
    """The options :func:`~comp_daemon.diagnosis.ladder.diagnose` takes, field for field
    (``infer_dir`` is ``infer_directions``)."""
    values = settings.model_dump()
    values["infer_directions"] = values.pop("infer_dir")
    return DiagnoseOptions(**values)
