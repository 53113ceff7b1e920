"""Tracker stations: every station's rows brought into one frame before any door fits anything.

A ``station`` column names the tracker's set-up of each row; a tracker moved between sessions is a
new station with its own frame (50° and 5 m away is ordinary). :func:`register_stations`:

1. the **reference** is the station with the most fit rows; every station with fit rows is placed in
   it by a first registration (the nominal twin's TCPs fitted rigidly onto the station's fit rows,
   :func:`~comp_daemon.estimation.registration.rigid_registration`, composed with the reference's);
2. the **joint** kinematic calibration of the fit rows
   (:func:`~comp_daemon.models.kinematic.calibrate_kinematic` with every station beside the
   reference corrected by six parameters, and the probe's orientations when the rows carry them)
   refines each station's frame together with the robot's parameters; the rows are mapped with
   the refined frames;
3. a station **without fit rows** (check rows only) is registered on its own rows alone: the joint
   calibration's TCPs fitted rigidly onto them, six parameters, said in the note. Its check error
   then judges the robot's shape, not its frame.

Every model kind then sees the rows in the reference station's frame. The kinematic calibration
and its effect forms (and the kinematic base of the kriging kinds) estimate the stations' frames
again, jointly with their own parameters (:mod:`comp_daemon.models.observations`); the kinds
without a joint estimate (Chebyshev, compliance, POE, the kriging layer, the diagnosis) take the
frames of step 2: registered on the kinematic calibration. The measured positions of further
targets and the probe's orientations turn with their station.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.table import Dataset
from comp_daemon.estimation.registration import frame_changes, rigid_registration
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import matrix_to_quat, quat_to_matrix
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.observations import MIN_STATION_ROWS
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = ["Station", "Stations", "judge_stations", "register_stations"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Station:
    """One station: its rows, how its frame was registered, and ``ref_T_station`` (4, 4), the
    motion that maps its measurements into the reference station's frame."""

    name: str
    fit_rows: int
    check_rows: int
    how: str  # "reference", "joint" (with the kinematic calibration), "own rows" (check rows only)
    ref_T_station: FloatArray

    def to_json(self) -> dict[str, Any]:
        rot = self.ref_T_station[:3, :3]
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))
        return {
            "fit_rows": self.fit_rows,
            "check_rows": self.check_rows,
            "registration": self.how,
            "parameters": 0 if self.how == "reference" else 6,
            "angle_deg": round(angle, 4),
            "shift_mm": round(float(np.linalg.norm(self.ref_T_station[:3, 3])), 3),
        }


@dataclass(frozen=True)
class Stations:
    """The stations of a campaign and the sentence that says how they were registered."""

    reference: str
    stations: tuple[Station, ...]
    fit_rms_mm: float  # the joint calibration's TCP RMS on the fit rows

    def by_name(self) -> dict[str, Station]:
        return {s.name: s for s in self.stations}

    @property
    def note(self) -> str:
        joint = [s.name for s in self.stations if s.how == "joint"]
        own = [s for s in self.stations if s.how == "own rows"]
        words = [
            f"{len(self.stations)} tracker stations, each in its own frame; the rows are in station "
            f"{self.reference}'s frame"
        ]
        if joint:
            words.append(
                f"{', '.join(joint)} registered jointly with the kinematic calibration of the fit rows "
                "(6 parameters each)"
            )
        for s in own:
            words.append(
                f"{s.name} has no fit rows: registered on its own {s.check_rows} check rows only "
                "(6 parameters, the calibrated robot's TCPs fitted rigidly onto them)"
            )
        return "; ".join(words)

    def to_json(self) -> dict[str, Any]:
        return {
            "reference": self.reference,
            "note": self.note,
            "stations": {s.name: s.to_json() for s in self.stations},
        }


def register_stations(
    dataset: Dataset, robot: RobotDescription, fit_rows: NDArray[np.int64], probe_sigma_deg: float
) -> tuple[Dataset, Stations | None]:
    """``dataset`` with every station's rows in the reference station's frame (module docstring),
    and the stations; the data set unchanged and None with fewer than two stations."""
    if dataset.station is None or len(set(dataset.station)) < 2:
        return dataset, None
    assert dataset.a_deg is not None and dataset.xyz_mm is not None
    source = dataset.source
    labels, index = np.unique(np.asarray(dataset.station, dtype=str), return_inverse=True)
    index = np.asarray(index, dtype=np.intp).reshape(-1)
    is_fit = np.zeros(len(dataset), dtype=bool)
    is_fit[fit_rows] = True
    n_fit = np.bincount(index[is_fit], minlength=len(labels))
    n_all = np.bincount(index, minlength=len(labels))
    few = [f"{labels[s]} ({n_fit[s]})" for s in range(len(labels)) if 0 < n_fit[s] < MIN_STATION_ROWS]
    if few:
        raise ValueError(
            f"{source}: station {', '.join(few)} fit rows: fewer than the {MIN_STATION_ROWS} that "
            "register a station's frame; give more, or mark all of its rows 'check'"
        )
    if not n_fit.any():
        raise ValueError(f"{source}: no station has fit rows")
    ref = int(max(np.flatnonzero(n_fit), key=lambda s: (n_fit[s], -s)))
    nominal = KinematicParams.from_robot(robot)
    p_nom = tcp_position_mm(nominal, axes_deg_to_q_rad(dataset.a_deg, nominal.sign))
    meas = dataset.xyz_mm

    def registration_of(s: int) -> FloatArray:
        rows = is_fit & (index == s)
        try:
            return rigid_registration(p_nom[rows], meas[rows])
        except ValueError as exc:
            raise ValueError(f"{source}: station {labels[s]}: {exc}") from None

    world_ref = registration_of(ref)
    ref_T: dict[int, FloatArray] = {
        int(s): np.asarray(world_ref @ _inverse(registration_of(int(s)))) for s in np.flatnonzero(n_fit)
    }
    first = _mapped(dataset, index, ref_T)
    rows = MeasuredRows.of_dataset(first, probe_sigma_deg=probe_sigma_deg).take(fit_rows)
    joint = calibrate_kinematic(
        robot,
        rows.a_deg,
        rows.xyz_mm,
        more_targets_mm=rows.more_xyz_mm,
        sigma_mm=rows.sigma_mm,
        frame="tracker",
        station=rows.station,
        station_names=rows.station_names,
        probe_r=rows.probe_r,
        probe_sigma_deg=probe_sigma_deg,
    )
    for name, moved in (joint.stations or {}).items():
        at = int(np.flatnonzero(labels == name)[0])
        ref_T[at] = np.asarray(moved @ ref_T[at])
    for s in (int(k) for k in np.flatnonzero(n_fit == 0)):
        own = index == s
        try:
            ref_T[s] = rigid_registration(meas[own], joint.model.predict_tcp_mm(dataset.a_deg[own]))
        except ValueError as exc:
            raise ValueError(f"{source}: station {labels[s]} (check rows only): {exc}") from None
    stations = tuple(
        Station(
            name=str(labels[s]),
            fit_rows=int(n_fit[s]),
            check_rows=int(n_all[s] - n_fit[s]),
            how="reference" if s == ref else ("joint" if n_fit[s] else "own rows"),
            ref_T_station=ref_T[s],
        )
        for s in range(len(labels))
    )
    return _mapped(dataset, index, ref_T), Stations(str(labels[ref]), stations, joint.rms_mm)


def judge_stations(
    dataset: Dataset, check_rows: NDArray[np.int64], predicted_mm: FloatArray, model: str
) -> tuple[list[str], dict[str, Any]]:
    """Each station's check error under ``model`` (its predictions ``predicted_mm`` of the check
    rows), and the stations whose error jumps and a rigid motion of their rows alone removes, named
    as frame changes (:func:`~comp_daemon.estimation.registration.frame_changes`): the sentences and the
    JSON. Nothing without a ``station`` column of two or more stations among the check rows."""
    if dataset.station is None or dataset.xyz_mm is None:
        return [], {}
    names = [dataset.station[int(i)] for i in check_rows]
    judged = frame_changes(names, predicted_mm, dataset.xyz_mm[check_rows])
    if not judged:
        return [], {}
    lines = [
        f"check rows per station ({model}): "
        + ", ".join(f"{j.station} {j.rms_mm:.4f} mm ({j.rows} rows)" for j in judged)
    ]
    lines += [j.describe() for j in judged if j.changed]
    return lines, {"model": model, "stations": {j.station: j.to_json() for j in judged}}


def _inverse(t: FloatArray) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def _mapped(dataset: Dataset, index: NDArray[np.intp], ref_T: dict[int, FloatArray]) -> Dataset:
    """The data set with each station's positions, further targets and probe orientations moved
    by its ``ref_T`` (stations without one stay as they are)."""
    assert dataset.xyz_mm is not None
    xyz = np.array(dataset.xyz_mm, dtype=float)
    more = None if dataset.more_xyz_mm is None else np.array(dataset.more_xyz_mm, dtype=float)
    probe = None if dataset.probe_q_wxyz is None else quat_to_matrix(dataset.probe_q_wxyz)
    for s, t in ref_T.items():
        rows = index == s
        xyz[rows] = xyz[rows] @ t[:3, :3].T + t[:3, 3]
        if more is not None:
            more[rows] = more[rows] @ t[:3, :3].T + t[:3, 3]
        if probe is not None:
            probe[rows] = t[:3, :3] @ probe[rows]
    return dataclasses.replace(
        dataset,
        xyz_mm=xyz,
        more_xyz_mm=more,
        probe_q_wxyz=None if probe is None else matrix_to_quat(probe),
    )
