""":func:`prepare_campaign`: a measurement data set made ready for a fit, an evaluation or a diagnosis.

What every door needs before it fits anything, decided once:

- **Approach directions** (:func:`prepare_directions`). The file's ``dir1..dir6`` columns, or,
  when it has none and the caller uses them, the sign of each axis' last motion in the pose order
  (:func:`comp_daemon.data.directions.infer_directions`: ``t_s`` order when there is a clock, else
  the file's row order, which is then *assumed* to be the order the robot visited the poses). An
  axis that has not moved yet has no known direction: its rows are marked unknown (0, no backlash
  offset there). :attr:`Directions.note` says all of it in one sentence.
- **Split**: the ``split`` column, else a reproducible draw of whole poses
  (:meth:`comp_daemon.data.table.Dataset.split_or_draw`), or, for a fit without a judgement
  (``hold_out=False``), the fit rows alone.
- **Row floor**: at least ``min_fit_rows`` fit rows (:data:`comp_daemon.models.registry.MIN_POSES`
  by default and at the least, the one floor of every door; the diagnosis asks for its geometric
  step's parameters), with the advice of how many rows to give when the check rows were drawn.
- **Frame**: the measurements are in the robot base frame when the nominal TCPs lie within
  :data:`~comp_daemon.estimation.registration.BASE_FRAME_MAX_RMS_MM` RMS of them on the fit rows, else
  in a tracker's frame, registered by the rigid motion that best maps the nominal TCPs onto them
  (``world_T_base``); ``frame="base"`` or ``"tracker"`` forces it. Positions that cannot be
  millimetres of this robot (metres, inches) are refused here
  (:func:`~comp_daemon.models.units.millimetre_problem`, the rule ``data check`` applies).
- **Targets**: how many reflectors each pose measures (``x, y, z`` and ``x2, y2, z2`` …).
- **Stations**: with a ``station`` column naming two or more tracker set-ups, every station's rows
  are brought into the reference station's frame, registered jointly with a kinematic calibration
  (:mod:`comp_daemon.preparation.stations`); a station with check rows only on its own rows.

Errors are :class:`CampaignError` (a ``ValueError``) naming the file and what is wrong.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.coverage import still_axes_note
from comp_daemon.data.directions import infer_directions
from comp_daemon.data.table import DEFAULT_CHECK_FRACTION, DEFAULT_SPLIT_SEED, Dataset, SplitChoice
from comp_daemon.estimation.registration import detect_frame, rigid_registration
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.registry import MIN_POSES
from comp_daemon.models.rows import DEFAULT_PROBE_SIGMA_DEG, MeasuredRows
from comp_daemon.models.units import millimetre_problem
from comp_daemon.preparation.stations import Stations, register_stations
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "CampaignError",
    "Directions",
    "PrepareOptions",
    "PreparedCampaign",
    "prepare_campaign",
    "prepare_directions",
]

FloatArray = NDArray[np.float64]
FrameChoice = Literal["auto", "base", "tracker"]


class CampaignError(ValueError):
    """A data set that cannot be prepared: the message names the file and what is wrong."""


@dataclass(frozen=True)
class Directions:
    """Where the approach directions of a data set come from.

    ``source``: ``"columns"`` (the file's dir1..dir6), ``"inferred"`` (from the pose order; the
    data set's ``dir`` holds them), or ``"none"`` (no directions: the file has none and they were
    not inferred). ``unknown`` (n, 6) marks inferred directions of an axis that had not moved yet
    (None unless inferred); ``order`` is ``"t_s"`` or ``"row order"`` when inferred.
    """

    source: Literal["columns", "inferred", "none"]
    unknown: NDArray[np.bool_] | None = None
    order: str | None = None
    note: str | None = None

    @property
    def inferred(self) -> bool:
        return self.source == "inferred"

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"source": self.source}
        if self.inferred:
            assert self.unknown is not None
            out["order"] = self.order
            out["assumed_row_order"] = self.order == "row order"
            out["unknown_per_axis"] = [int(c) for c in self.unknown.sum(axis=0)]
            out["note"] = self.note
        return out


def prepare_directions(
    dataset: Dataset, *, need: bool = True, infer: bool = True
) -> tuple[Dataset, Directions]:
    """``dataset`` with its approach directions, and where they come from.

    The file's columns when it has them; else, when the caller ``need``s them and may ``infer``
    them, the sign of each axis' last motion in the pose order (module docstring); else none.
    """
    if dataset.dir is not None:
        return dataset, Directions("columns")
    if not (need and infer) or dataset.a_deg is None:
        return dataset, Directions("none")
    inferred = infer_directions(dataset.a_deg, dataset.t_s)
    out = dataclasses.replace(dataset, dir=inferred.dir)
    return out, Directions("inferred", inferred.assumed, inferred.order, inferred.describe())


@dataclass(frozen=True)
class PrepareOptions:
    """How a door prepares a campaign.

    ``need_directions``: the caller uses approach directions (a backlash model, the diagnosis), so
    they are inferred from the pose order when the file has none and ``infer_directions`` allows.
    ``hold_out``: draw check rows when the file has no ``split`` column (else every row is a fit
    row). ``require_check``: refuse a campaign without check rows. ``min_fit_rows`` and
    ``min_fit_rows_for``: the row floor and what needs it, in the refusal's words ("fewer than the
    3 poses a fit needs"). ``probe_sigma_deg``: a 6-DOF probe's orientation σ per axis, which weighs
    its ``qw…qz`` against the positions (:mod:`comp_daemon.models.observations`).
    """

    frame: FrameChoice = "auto"
    need_directions: bool = False
    infer_directions: bool = True
    hold_out: bool = True
    require_check: bool = True
    min_fit_rows: int = MIN_POSES
    min_fit_rows_for: str = "poses a fit needs"
    seed: int = DEFAULT_SPLIT_SEED
    check_fraction: float = DEFAULT_CHECK_FRACTION
    probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG

    def __post_init__(self) -> None:
        if self.frame not in ("auto", "base", "tracker"):
            raise ValueError(f"frame must be auto, base or tracker, got {self.frame!r}")
        if self.min_fit_rows < MIN_POSES:  # the one floor: a door may ask for more, never for less
            raise ValueError(
                f"min_fit_rows must be at least MIN_POSES ({MIN_POSES}), got {self.min_fit_rows}"
            )


@dataclass(frozen=True)
class PreparedCampaign:
    """A measurement data set ready for every door (module docstring).

    ``dataset`` carries the directions (inferred ones filled in); ``data_sha256`` is the file's as
    read (before any inference). ``frame`` is where the positions were measured; ``world_T_base``
    (4, 4) the nominal twin's registration to them on the fit rows (identity in the base frame);
    ``nominal_fit_rms_mm`` the registered nominal twin's RMS on the fit rows. ``stations``: with a
    ``station`` column naming two or more, how each was registered (the data set's positions are
    then in the reference station's frame, :mod:`comp_daemon.preparation.stations`).
    """

    dataset: Dataset
    data_sha256: str
    directions: Directions
    split: SplitChoice
    frame: Literal["base", "tracker"]
    world_T_base: FloatArray
    nominal_fit_rms_mm: float
    still_axes: str | None
    stations: Stations | None = None
    probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG

    @property
    def source(self) -> str:
        return self.dataset.source

    @property
    def fit_rows(self) -> NDArray[np.int64]:
        return np.asarray(self.split.fit_rows, dtype=np.int64)

    @property
    def check_rows(self) -> NDArray[np.int64]:
        return np.asarray(self.split.check_rows, dtype=np.int64)

    @property
    def n_targets(self) -> int:
        """Reflectors measured per pose (1 + the further ``x2, y2, z2`` …)."""
        return self.dataset.n_reflectors

    @cached_property
    def measured(self) -> MeasuredRows:
        """Every row of the data set as measured rows (:meth:`MeasuredRows.of_dataset`: every
        target, the directions with unknown ones 0, the probe's σ), built once."""
        return MeasuredRows.of_dataset(self.dataset, self.directions.unknown, self.probe_sigma_deg)

    def rows(self, rows: NDArray[np.int64]) -> MeasuredRows:
        """These rows of :attr:`measured`."""
        return self.measured.take(rows)

    def describe(self) -> list[str]:
        """The sentences a door says about the preparation (directions, axes that stand still,
        stations)."""
        stations = None if self.stations is None else self.stations.note
        return [s for s in (self.directions.note, self.still_axes, stations) if s]


def prepare_campaign(
    dataset: Dataset, robot: RobotDescription, options: PrepareOptions | None = None
) -> PreparedCampaign:
    """Prepare a measurement data set for a fit, an evaluation or a diagnosis (module docstring)."""
    options = options or PrepareOptions()
    source = dataset.source
    if dataset.a_deg is None or dataset.xyz_mm is None:
        raise CampaignError(f"{source}: a campaign needs axis values a1..a6 and measured x, y, z")
    data_sha256 = dataset.content_sha256
    dataset, directions = prepare_directions(
        dataset, need=options.need_directions, infer=options.infer_directions
    )
    split = _split(dataset, options)
    fit_rows = np.asarray(split.fit_rows)
    nominal = KinematicParams.from_robot(robot)
    assert dataset.a_deg is not None and dataset.xyz_mm is not None
    scale = millimetre_problem(robot, dataset.a_deg, dataset.xyz_mm, dataset.station)  # data check's rule
    if scale is not None:
        raise CampaignError(f"{source}: {scale}")
    _check_floor(dataset, split, options)
    try:
        dataset, stations = register_stations(dataset, robot, fit_rows, options.probe_sigma_deg)
    except ValueError as exc:
        raise CampaignError(str(exc)) from None
    assert dataset.a_deg is not None and dataset.xyz_mm is not None
    p_nom = tcp_position_mm(nominal, axes_deg_to_q_rad(dataset.a_deg[fit_rows], nominal.sign))
    p_meas = dataset.xyz_mm[fit_rows]
    frame: Literal["base", "tracker"] = (
        detect_frame(p_nom, p_meas) if options.frame == "auto" else options.frame
    )
    # past the floor there are at least MIN_POSES fit rows: enough to register the frame on
    world_T_base = rigid_registration(p_nom, p_meas) if frame == "tracker" else np.eye(4)
    p_reg = p_nom @ world_T_base[:3, :3].T + world_T_base[:3, 3]
    rms = float(np.sqrt(np.mean(np.sum((p_meas - p_reg) ** 2, axis=1))))
    return PreparedCampaign(
        dataset=dataset,
        data_sha256=data_sha256,
        directions=directions,
        split=split,
        frame=frame,
        world_T_base=world_T_base,
        nominal_fit_rms_mm=rms,
        still_axes=still_axes_note(dataset, fit_rows) if len(fit_rows) else None,
        stations=stations,
        probe_sigma_deg=options.probe_sigma_deg,
    )


def _split(dataset: Dataset, options: PrepareOptions) -> SplitChoice:
    """The fit and check rows; refused without check rows when they are required."""
    source, n = dataset.source, len(dataset)
    if options.hold_out:
        split = dataset.split_or_draw(seed=options.seed, check_fraction=options.check_fraction)
    else:
        fit, check = dataset.fit_rows(), dataset.check_rows()
        how = "split column" if dataset.split is not None else "no split column: every row"
        split = SplitChoice(fit, check, False, None, f"{source}: {how} gives {len(fit)} fit rows")
    if options.require_check and len(split.check_rows) == 0:
        if split.drawn:
            raise CampaignError(
                f"{source}: the {n} rows are one pose (repeats): none left to hold out as check rows; "
                "give poses spread over the workspace"
            )
        raise CampaignError(f"{source}: no check rows to judge on (the split marks no row 'check')")
    return split


def _check_floor(dataset: Dataset, split: SplitChoice, options: PrepareOptions) -> None:
    """Refuse fewer fit rows than ``options.min_fit_rows``, saying how many rows to give."""
    source, n = dataset.source, len(dataset)
    n_fit, floor = len(split.fit_rows), options.min_fit_rows
    if n_fit < floor:
        if split.drawn:
            need = int(np.ceil(floor / (1.0 - options.check_fraction)))
            how = (
                f"{len(split.check_rows)} of the {n} rows are held out as check rows; give at least "
                f"{need} rows, or a split column with at least {floor} 'fit' rows"
            )
        elif dataset.split is not None:
            how = f"the split column marks {n_fit} rows 'fit'; at least {floor} are needed"
        else:
            how = f"at least {floor} are needed"
        raise CampaignError(
            f"{source}: {n_fit} fit rows, fewer than the {floor} {options.min_fit_rows_for} ({how})"
        )
