"""The export formats by name: parameter listings and target lists, each a writer and a reader."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from comp_daemon.models.export.krl import format_krl_targets, format_kuka, parse_krl_targets, parse_kuka
from comp_daemon.models.export.params import ControllerParams, format_csv, parse_csv
from comp_daemon.models.export.rapid import format_abb, format_rapid_targets, parse_abb, parse_rapid_targets
from comp_daemon.models.export.targets import TargetList, format_csv_targets, parse_csv_targets

__all__ = ["PARAM_FORMATS", "TARGET_FORMATS", "TARGET_SUFFIX", "write_targets"]

#: format -> (writer, reader) of parameter listings
PARAM_FORMATS: dict[str, tuple[Callable[[ControllerParams], str], Callable[[str, str], ControllerParams]]] = {
    "kuka": (format_kuka, parse_kuka),
    "abb": (format_abb, parse_abb),
    "csv": (format_csv, parse_csv),
}
#: format -> reader of target lists (writers: :func:`write_targets`)
TARGET_FORMATS: dict[str, Callable[[str, str], TargetList]] = {
    "krl": parse_krl_targets,
    "rapid": parse_rapid_targets,
    "csv": parse_csv_targets,
}
TARGET_SUFFIX = {"krl": ".dat", "rapid": ".mod", "csv": ".csv"}


def write_targets(fmt: str, targets: TargetList, module: str, header: Sequence[str] = ()) -> str:
    """The text of ``targets`` in ``fmt`` (krl, rapid, csv); ``module`` names the KRL / RAPID module,
    ``header`` is written as comment lines (not in the CSV, which stays a plain target file)."""
    if fmt == "krl":
        return format_krl_targets(targets, module, header)
    if fmt == "rapid":
        return format_rapid_targets(targets, module, header)
    if fmt == "csv":
        return format_csv_targets(targets)
    raise ValueError(f"unknown target format '{fmt}' (known: {', '.join(TARGET_FORMATS)})")
