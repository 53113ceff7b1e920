"""The export formats by name: parameter listings and target lists, each a writer and a reader."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from comp_daemon.export.krl import format_krl_targets, format_kuka, parse_krl_targets, parse_kuka
from comp_daemon.export.params import ControllerParams, format_csv, model_of, parse_csv
from comp_daemon.export.rapid import format_abb, format_rapid_targets, parse_abb, parse_rapid_targets
from comp_daemon.export.targets import TargetList, format_csv_targets, parse_csv_targets
from comp_daemon.models.kinematic import KinematicModel

__all__ = [
    "PARAM_FORMATS",
    "ROUND_TRIP_MM",
    "TARGET_FORMATS",
    "params_text",
    "write_targets",
]

#: the largest TCP difference (mm) a parameter listing read back may make
ROUND_TRIP_MM = 1e-6

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


def params_text(listing: ControllerParams, model: KinematicModel, fmt: str) -> tuple[str, float]:
    """The text of ``listing`` in ``fmt`` (kuka, abb, csv), read back and rebuilt, and the largest
    TCP difference (mm) of the rebuilt model from ``model`` at every axis's lower and upper limits
    and the middle of the ranges; ValueError when that exceeds :data:`ROUND_TRIP_MM`."""
    if fmt not in PARAM_FORMATS:
        raise ValueError(f"unknown parameter format '{fmt}' (known: {', '.join(PARAM_FORMATS)})")
    write, read = PARAM_FORMATS[fmt]
    text = write(listing)
    back = model_of(read(text, fmt), model.robot)
    limits = model.robot.axis_limits_deg
    probe = np.concatenate([limits.T, limits.mean(axis=1)[None, :]])
    diff = float(np.max(np.abs(back.predict_tcp_mm(probe) - model.predict_tcp_mm(probe))))
    if diff > ROUND_TRIP_MM:
        raise ValueError(f"the {fmt} listing read back moves the TCP by {diff:.3g} mm")
    return text, diff
