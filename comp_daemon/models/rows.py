"""The measured rows of a campaign: one type for every model fit, the preparation and the diagnosis.

A :class:`MeasuredRows` holds, row by row, what was commanded and what was measured, with the
units in the names: the axis values ``a_deg`` (n, 6, the controller's convention), the measured
TCP ``xyz_mm`` (n, 3), and the optional columns

- ``dir`` (n, 6): approach directions −1 / +1, 0 where unknown (an inferred direction of an axis
  that has not moved yet); None without directions;
- ``payload_kg`` (n,); ``temp_c`` (n,) or None;
- ``more_xyz_mm`` (n, K − 1, 3): the further targets (reflectors) on the flange, in the frame of
  ``xyz_mm``; None with one target, and None once the targets are rows of their own
  (:meth:`MeasuredRows.stack_targets`);
- ``sigma_mm`` (n,): each row's declared position σ per axis;
- ``station`` (n,): each row's tracker station, an index into ``station_names``;
- ``probe_r`` (n, 3, 3): a 6-DOF probe's measured rotations, observed with the orientation σ
  ``probe_sigma_deg`` per axis;
- ``pose_group`` (n,): numbers the distinct commanded poses (repeats of a pose share one), the unit
  of cross-validation folds and of the cluster-robust covariance;
- ``clock`` (n,): the campaign clock of the time effects, hours since the first ``t_s``, or the row
  number when the campaign has no times (``clock_name``: ``"t_s"`` or ``"pose_order"``); None for
  rows given without a campaign;
- ``target`` (n,): with the targets stacked, each row's target (0 = the TCP, the twin's tool), and
  ``target_offsets_mm`` (K − 1, 3) the further targets' places in the flange frame.

:meth:`MeasuredRows.of_dataset` is the one place the columns of a
:class:`~comp_daemon.data.table.Dataset` become rows; :meth:`~MeasuredRows.take` keeps some rows
with every column, :meth:`~MeasuredRows.stack_targets` makes every target a row of its own. What
the effects derive from the rows (their inputs, gravity torques, which joints move the TCP) is
built from them in :mod:`comp_daemon.models.effects.twin`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.table import Dataset
from comp_daemon.kinematics.so3 import quat_to_matrix
from comp_daemon.models.base import ErrorModel, as_axes, further_targets, measured_positions

__all__ = ["DEFAULT_PROBE_SIGMA_DEG", "MeasuredRows"]

FloatArray = NDArray[np.float64]

#: a 6-DOF probe's orientation σ per axis (deg) unless the door is told otherwise: the class of a
#: tracker's 6-DOF probe (Leica T-Mac: ±0.01° stated)
DEFAULT_PROBE_SIGMA_DEG = 0.01

_PER_ROW = {"per_row": True}


@dataclass(frozen=True, slots=True)
class MeasuredRows:
    """Measured rows, in data-set order (module docstring for every column)."""

    a_deg: FloatArray = field(metadata=_PER_ROW)
    xyz_mm: FloatArray = field(metadata=_PER_ROW)
    dir: FloatArray | None = field(default=None, metadata=_PER_ROW)
    payload_kg: FloatArray = field(default_factory=lambda: np.zeros(0), metadata=_PER_ROW)
    temp_c: FloatArray | None = field(default=None, metadata=_PER_ROW)
    more_xyz_mm: FloatArray | None = field(default=None, metadata=_PER_ROW)
    sigma_mm: FloatArray | None = field(default=None, metadata=_PER_ROW)
    station: NDArray[np.intp] | None = field(default=None, metadata=_PER_ROW)
    station_names: tuple[str, ...] | None = None
    probe_r: FloatArray | None = field(default=None, metadata=_PER_ROW)
    probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG
    pose_group: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64), metadata=_PER_ROW)
    clock: FloatArray | None = field(default=None, metadata=_PER_ROW)
    clock_name: str = "pose_order"
    target: NDArray[np.int64] | None = field(default=None, metadata=_PER_ROW)
    target_offsets_mm: FloatArray | None = None

    def __post_init__(self) -> None:
        """Shapes checked; ``payload_kg`` given as a number (or not at all: 0) becomes (n,); pose
        groups default to identical axis values."""
        put = object.__setattr__
        a = as_axes(self.a_deg)
        n = a.shape[0]
        put(self, "a_deg", a)
        put(self, "xyz_mm", measured_positions(self.xyz_mm, n))
        if self.more_xyz_mm is not None:
            put(self, "more_xyz_mm", further_targets(self.more_xyz_mm, n))
        payload = np.asarray(self.payload_kg, dtype=float)
        payload = np.zeros(n) if payload.shape == (0,) else payload
        if payload.ndim > 1 or (payload.ndim == 1 and payload.shape[0] != n):
            raise ValueError(f"payload_kg: expected a number or shape ({n},), got {payload.shape}")
        put(self, "payload_kg", np.array(np.broadcast_to(payload, (n,))))
        if len(self.pose_group) == 0 < n:  # not given: by identical axis values
            _, group = np.unique(a, axis=0, return_inverse=True)
            put(self, "pose_group", np.asarray(group, dtype=np.int64).reshape(-1))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.metadata.get("per_row") and value is not None and np.shape(value)[0] != n:
                got = np.shape(value)[0]
                raise ValueError(f"{f.name}: expected {n} rows like the axis values, got {got}")

    @property
    def n(self) -> int:
        return int(self.a_deg.shape[0])

    def __len__(self) -> int:
        return self.n

    @classmethod
    def of_dataset(
        cls,
        dataset: Dataset,
        unknown_dir: NDArray[np.bool_] | None = None,
        probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG,
    ) -> MeasuredRows:
        """Every row of a measurement data set (axis values and positions required).

        ``unknown_dir`` (n, 6) marks approach directions that are not known (set to 0); pose groups
        by ``pose_id``, else by identical axis values; stations numbered in sorted order of their
        names; the probe's quaternions ``qw…qz`` as rotation matrices, observed with
        ``probe_sigma_deg``; the clock from ``t_s``, else the row order.
        """
        if dataset.a_deg is None or dataset.xyz_mm is None:
            raise ValueError(f"{dataset.source}: measured rows need axis values a1..a6 and measured x, y, z")
        station, names = None, None
        if dataset.station is not None:
            labels, index = np.unique(np.asarray(dataset.station, dtype=str), return_inverse=True)
            station, names = np.asarray(index, dtype=np.intp).reshape(-1), tuple(str(s) for s in labels)
        if dataset.pose_id is not None:
            _, group = np.unique(np.asarray(dataset.pose_id, dtype=str), return_inverse=True)
        else:
            _, group = np.unique(dataset.a_deg, axis=0, return_inverse=True)
        n = len(dataset.a_deg)
        if dataset.t_s is not None:  # finite: the data set checks it
            t = np.asarray(dataset.t_s, dtype=float)
            clock, clock_name = (t - t.min()) / 3600.0, "t_s"
        else:
            clock, clock_name = np.arange(n, dtype=float), "pose_order"
        direction = None
        if dataset.dir is not None:
            direction = np.array(dataset.dir, dtype=float)
            if unknown_dir is not None:
                direction[unknown_dir] = 0.0
        return cls(
            np.array(dataset.a_deg, dtype=float),
            np.array(dataset.xyz_mm, dtype=float),
            dir=direction,
            payload_kg=np.array(dataset.payload_kg, dtype=float),
            temp_c=None if dataset.temp_c is None else np.array(dataset.temp_c, dtype=float),
            more_xyz_mm=None if dataset.more_xyz_mm is None else np.array(dataset.more_xyz_mm, dtype=float),
            sigma_mm=None if dataset.sigma_mm is None else np.array(dataset.sigma_mm, dtype=float),
            station=station,
            station_names=names,
            probe_r=None if dataset.probe_q_wxyz is None else quat_to_matrix(dataset.probe_q_wxyz),
            probe_sigma_deg=probe_sigma_deg,
            pose_group=np.asarray(group, dtype=np.int64).reshape(-1),
            clock=clock,
            clock_name=clock_name,
        )

    def take(self, rows: NDArray[np.intp] | NDArray[np.int64]) -> MeasuredRows:
        """These rows only, every column."""
        return self._per_row(lambda _, value: value[rows])

    def stack_targets(self, more_xyz_mm: FloatArray, offsets_mm: FloatArray) -> MeasuredRows:
        """Every target as rows of their own: these rows (target 0, the TCP), then each further
        target's (``more_xyz_mm`` (n, K − 1, 3) measured, ``offsets_mm`` (K − 1, 3) its place in
        the flange frame); row ``i + k·n`` is target ``k`` of pose ``i``. Every other column is
        repeated for each target; ``more_xyz_mm`` is None afterwards (the targets are rows)."""
        more = further_targets(more_xyz_mm, self.n)
        k = 1 + more.shape[1]

        def tiled(name: str, value: Any) -> Any:
            if name == "xyz_mm":
                return np.concatenate([value, *np.moveaxis(more, 1, 0)], axis=0)
            if name == "more_xyz_mm":
                return None
            return np.concatenate([value] * k, axis=0)

        stacked = self._per_row(tiled)
        return dataclasses.replace(
            stacked,
            target=np.repeat(np.arange(k, dtype=np.int64), self.n),
            target_offsets_mm=np.asarray(offsets_mm, dtype=float).reshape(k - 1, 3),
        )

    def by_target(self) -> list[tuple[NDArray[np.int64], MeasuredRows, FloatArray | None]]:
        """(rows, their measured rows, the target's flange-frame place or None for the TCP) per
        target; one entry holding every row when the targets are not stacked."""
        if self.target is None or self.target_offsets_mm is None:
            return [(np.arange(self.n), self, None)]
        out = []
        for k in range(len(self.target_offsets_mm) + 1):
            rows = np.flatnonzero(self.target == k)
            if len(rows):
                sub = dataclasses.replace(self.take(rows), target=None, target_offsets_mm=None)
                out.append((rows, sub, None if k == 0 else self.target_offsets_mm[k - 1]))
        return out

    def same_poses(self, other: MeasuredRows) -> bool:
        """Whether two sets of rows are the same poses in the same order (one twin serves both)."""

        def same(x: Any, y: Any) -> bool:
            return (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))

        return (
            np.array_equal(self.a_deg, other.a_deg)
            and np.array_equal(self.payload_kg, other.payload_kg)
            and same(self.dir, other.dir)
            and same(self.temp_c, other.temp_c)
            and same(self.clock, other.clock)
        )

    def errors(self, model: ErrorModel) -> FloatArray:
        """(n, 3) measured − predicted of ``model`` on these rows (mm)."""
        return self.xyz_mm - model.predict_tcp_mm(self.a_deg, self.dir, self.payload_kg, self.temp_c)

    def _per_row(self, each: Any) -> MeasuredRows:
        """These rows with ``each(name, column)`` in place of every per-row column that is set."""
        changed = {
            f.name: each(f.name, getattr(self, f.name))
            for f in dataclasses.fields(self)
            if f.metadata.get("per_row") and getattr(self, f.name) is not None
        }
        return dataclasses.replace(self, **changed)
