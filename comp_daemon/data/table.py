"""The :class:`Dataset` of ``docs/data-format.md`` and its canonical CSV form (the writer).

Units are those of the spec and are carried in the field names: axis values ``a_deg`` (controller
convention, KUKA A1..A6, degrees), measured TCP ``xyz_mm`` (mm), grating readings ``g_deg`` (deg),
``payload_kg``, ``temp_c``, ``t_s``, further targets (reflectors) on the flange ``more_xyz_mm`` (mm),
target pose ``target_xyz_mm`` (mm) and ``target_abc_deg``
(KUKA A, B, C in deg: rotations about z, y, x). Rows are indexed 0..n-1 in arrays;
``row_numbers`` maps them back to the 1-based row of the file they came from (header = row 1),
or to the 1-based record number for JSON records (``row_label == "record"``).

A :class:`Dataset` is valid by construction (shapes, finite numbers, ``dir`` in {-1, +1},
``split`` in {fit, check}, ``payload_kg`` >= 0); only the robot's axis limits and a minimum row
count depend on the caller and are checked by the readers (:mod:`comp_daemon.data.readers`).
Two data sets are equal when their canonical CSV text is equal (``source``, ``row_numbers`` and
``row_label`` are provenance, not content); that text is what :attr:`Dataset.content_sha256`
hashes and what :func:`write_dataset` writes: columns in the order of the spec's table, then
unknown columns in their original order, floats as ``repr`` (shortest text that reads back
bit-exact), ``payload_kg`` only when some payload is non-zero.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import os
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType
from typing import Any, TextIO

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.common.atomic import write_text_atomic
from comp_daemon.data.columns import (
    AXIS_COLUMNS,
    DIR_COLUMNS,
    GRATING_COLUMNS,
    KNOWN_COLUMNS,
    QUATERNION_COLUMNS,
    QUATERNION_NORM_TOL,
    TARGET_ABC_COLUMNS,
    TARGET_XYZ_COLUMNS,
    XYZ_COLUMNS,
    is_reflector_column,
    reflector_columns,
)

__all__ = [
    "DEFAULT_CHECK_FRACTION",
    "DEFAULT_SPLIT_SEED",
    "SPLIT_VALUES",
    "Dataset",
    "FloatArray",
    "IntArray",
    "SplitChoice",
    "dataset_to_csv",
    "write_dataset",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

DEFAULT_SPLIT_SEED = 20240601
DEFAULT_CHECK_FRACTION = 0.2
SPLIT_VALUES = ("fit", "check")


# ---------------------------------------------------------------------------------------------
# The data set
# ---------------------------------------------------------------------------------------------
def _frozen(array: ArrayLike, dtype: Any, shape: tuple[int | None, ...], name: str) -> NDArray[Any]:
    out = np.array(array, dtype=dtype, copy=True)
    if out.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, out.shape, strict=True)):
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"Dataset.{name}: expected shape {want}, got {out.shape}")
    out.flags.writeable = False
    return out


def _require_finite(array: NDArray[Any], name: str) -> None:
    bad = ~np.isfinite(array)
    if bad.any():
        index = np.argwhere(bad)[0]
        raise ValueError(f"Dataset.{name}: non-finite value at index {tuple(int(i) for i in index)}")


@dataclass(frozen=True, eq=False)
class Dataset:
    """One measurement campaign or one batch of targets; arrays are read-only, rows first.

    ``a_deg`` is ``None`` only for a target file that gives the wanted pose (``tx, ty, tz``)
    instead of axis values. ``g_present`` (6,) says which grating columns the file had; absent
    columns hold NaN in ``g_deg`` (``g_deg`` is ``None`` when none is present). ``payload_kg``
    defaults to zeros. ``extra`` holds unknown columns, verbatim, in file order.

    ``more_xyz_mm`` (n, K − 1, 3) holds the further targets (reflectors) fixed to the same flange,
    columns ``x2, y2, z2`` … ``xK, yK, zK``, in the frame of ``xyz_mm`` (target 1);
    :attr:`reflectors_mm` stacks all K as (n, K, 3).

    ``station`` names each row's tracker set-up (rows of one station share a measurement frame);
    ``probe_q_wxyz`` (n, 4) is a 6-DOF probe's orientation, a unit quaternion (w first) in the frame
    of ``xyz_mm`` (columns ``qw, qx, qy, qz``); ``sigma_mm`` (n,) each row's declared position σ
    per axis (mm, > 0).
    """

    a_deg: FloatArray | None
    xyz_mm: FloatArray | None = None
    dir: NDArray[np.int8] | None = None
    g_deg: FloatArray | None = None
    g_present: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    payload_kg: FloatArray = field(default_factory=lambda: np.zeros(0))
    temp_c: FloatArray | None = None
    t_s: FloatArray | None = None
    split: NDArray[np.str_] | None = None
    repeat: IntArray | None = None
    pose_id: tuple[str, ...] | None = None
    target_xyz_mm: FloatArray | None = None
    target_abc_deg: FloatArray | None = None
    more_xyz_mm: FloatArray | None = None
    station: tuple[str, ...] | None = None
    probe_q_wxyz: FloatArray | None = None
    sigma_mm: FloatArray | None = None
    extra: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    source: str = "<memory>"
    row_numbers: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    row_label: str = "row"

    def __post_init__(self) -> None:
        put = object.__setattr__
        if self.a_deg is not None:
            a_deg = _frozen(self.a_deg, np.float64, (None, 6), "a_deg")
            put(self, "a_deg", a_deg)
            n = len(a_deg)
        elif self.target_xyz_mm is not None:
            n = len(_frozen(self.target_xyz_mm, np.float64, (None, 3), "target_xyz_mm"))
        else:
            raise ValueError("Dataset: needs axis values a_deg or target positions target_xyz_mm")

        for name, width in (("xyz_mm", 3), ("target_xyz_mm", 3), ("target_abc_deg", 3)):
            value = getattr(self, name)
            if value is not None:
                put(self, name, _frozen(value, np.float64, (n, width), name))
        for name in ("temp_c", "t_s"):
            value = getattr(self, name)
            if value is not None:
                put(self, name, _frozen(value, np.float64, (n,), name))
        payload = np.asarray(self.payload_kg, dtype=np.float64)
        payload = np.zeros(n) if payload.shape == (0,) else payload
        put(self, "payload_kg", _frozen(payload, np.float64, (n,), "payload_kg"))
        for name in ("a_deg", "xyz_mm", "target_xyz_mm", "target_abc_deg", "temp_c", "t_s", "payload_kg"):
            value = getattr(self, name)
            if value is not None:
                _require_finite(value, name)
        self._init_reflectors(n)
        if self.target_abc_deg is not None and self.target_xyz_mm is None:
            raise ValueError("Dataset.target_abc_deg: needs target_xyz_mm")
        if (payload < 0).any():
            raise ValueError("Dataset.payload_kg: must be >= 0")

        if self.dir is not None:
            raw_dir = np.asarray(self.dir)
            if raw_dir.size and not np.isin(raw_dir, (-1, 1)).all():
                raise ValueError("Dataset.dir: values must be -1 or +1")
            put(self, "dir", _frozen(raw_dir, np.int8, (n, 6), "dir"))

        self._init_gratings(n)

        if self.split is not None:
            raw_split = _frozen(self.split, np.str_, (n,), "split")
            if raw_split.size and not np.isin(raw_split, SPLIT_VALUES).all():
                raise ValueError("Dataset.split: values must be 'fit' or 'check'")
            put(self, "split", _frozen(raw_split, "<U5", (n,), "split"))
        if self.repeat is not None:
            raw_repeat = np.asarray(self.repeat)
            if raw_repeat.size and (
                not np.array_equal(raw_repeat, np.round(raw_repeat)) or (raw_repeat < 0).any()
            ):
                raise ValueError("Dataset.repeat: values must be integers >= 0")
            put(self, "repeat", _frozen(raw_repeat, np.int64, (n,), "repeat"))
        if self.pose_id is not None:
            pose_id = tuple(str(p) for p in self.pose_id)
            if len(pose_id) != n:
                raise ValueError(f"Dataset.pose_id: expected {n} entries, got {len(pose_id)}")
            put(self, "pose_id", pose_id)
        self._init_probe(n)

        extra: dict[str, tuple[str, ...]] = {}
        known = set(KNOWN_COLUMNS)
        for key, values in self.extra.items():
            if not key or key != key.strip() or key.lower() in known or is_reflector_column(key.lower()):
                raise ValueError(f"Dataset.extra: {key!r} cannot be the name of an extra column")
            column = tuple(str(v) for v in values)
            if len(column) != n:
                raise ValueError(f"Dataset.extra[{key!r}]: expected {n} entries, got {len(column)}")
            extra[key] = column
        put(self, "extra", MappingProxyType(extra))

        rows = np.asarray(self.row_numbers, dtype=np.int64)
        rows = np.arange(2, n + 2) if rows.shape == (0,) else rows
        put(self, "row_numbers", _frozen(rows, np.int64, (n,), "row_numbers"))
        if self.row_label not in ("row", "record"):
            raise ValueError("Dataset.row_label: 'row' or 'record'")

    def _init_reflectors(self, n: int) -> None:
        if self.more_xyz_mm is None:
            return
        more = np.array(self.more_xyz_mm, dtype=np.float64, copy=True)
        if more.ndim != 3 or more.shape[0] != n or more.shape[2] != 3:
            raise ValueError(
                f"Dataset.more_xyz_mm: expected shape (n, K - 1, 3) with n = {n}, got {more.shape}"
            )
        if more.shape[1] == 0:
            object.__setattr__(self, "more_xyz_mm", None)
            return
        if self.xyz_mm is None:
            raise ValueError("Dataset.more_xyz_mm: further targets need the first one (xyz_mm)")
        _require_finite(more, "more_xyz_mm")
        more.flags.writeable = False
        object.__setattr__(self, "more_xyz_mm", more)

    def _init_probe(self, n: int) -> None:
        """Validate ``station``, ``probe_q_wxyz`` and ``sigma_mm``."""
        put = object.__setattr__
        if self.station is not None:
            station = tuple(str(s) for s in self.station)
            if len(station) != n or not all(s and s == s.strip() for s in station):
                raise ValueError(f"Dataset.station: {n} non-empty names without surrounding spaces expected")
            put(self, "station", station)
        if self.probe_q_wxyz is not None:
            if self.xyz_mm is None:
                raise ValueError("Dataset.probe_q_wxyz: a probe's orientation needs its position xyz_mm")
            q = _frozen(self.probe_q_wxyz, np.float64, (n, 4), "probe_q_wxyz")
            _require_finite(q, "probe_q_wxyz")
            if (np.abs(np.linalg.norm(q, axis=1) - 1.0) > QUATERNION_NORM_TOL).any():
                raise ValueError("Dataset.probe_q_wxyz: every row must be a unit quaternion")
            put(self, "probe_q_wxyz", q)
        if self.sigma_mm is not None:
            sigma = _frozen(self.sigma_mm, np.float64, (n,), "sigma_mm")
            _require_finite(sigma, "sigma_mm")
            if (sigma <= 0).any():
                raise ValueError("Dataset.sigma_mm: must be > 0")
            put(self, "sigma_mm", sigma)

    @property
    def n_reflectors(self) -> int:
        """How many targets (reflectors) each row measures: 0 without x, y, z, else 1 + the further ones."""
        if self.xyz_mm is None:
            return 0
        return 1 + (0 if self.more_xyz_mm is None else int(self.more_xyz_mm.shape[1]))

    @property
    def reflectors_mm(self) -> FloatArray | None:
        """(n, K, 3) every target's measured position (target 1 = ``xyz_mm``); None without x, y, z."""
        if self.xyz_mm is None:
            return None
        if self.more_xyz_mm is None:
            return self.xyz_mm[:, None, :]
        return np.concatenate([self.xyz_mm[:, None, :], self.more_xyz_mm], axis=1)

    def _init_gratings(self, n: int) -> None:
        put = object.__setattr__
        if self.g_deg is None:
            if np.asarray(self.g_present).any():
                raise ValueError("Dataset.g_present: grating columns marked present but g_deg is None")
            put(self, "g_present", _frozen(np.zeros(6, bool), np.bool_, (6,), "g_present"))
            return
        g_deg = _frozen(self.g_deg, np.float64, (n, 6), "g_deg")
        present = np.asarray(self.g_present, dtype=bool)
        if present.shape == (0,):
            present = ~np.isnan(g_deg).all(axis=0) if n else np.zeros(6, bool)
        present = _frozen(present, np.bool_, (6,), "g_present")
        if not np.isnan(g_deg[:, ~present]).all():
            raise ValueError("Dataset.g_deg: columns that are not present must hold NaN")
        _require_finite(g_deg[:, present], "g_deg (present columns)")
        put(self, "g_present", present)
        put(self, "g_deg", g_deg if present.any() else None)

    # ---- size and content --------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.row_numbers)

    @property
    def n(self) -> int:
        return len(self)

    @property
    def columns(self) -> tuple[str, ...]:
        """The columns this data set writes, in the writer's order (the canonical CSV's header)."""
        text = self._canonical_csv
        return tuple(next(csv.reader([text[: text.index("\n")]])))

    @cached_property
    def _canonical_csv(self) -> str:
        """The CSV text, rendered once (the data set is immutable)."""
        return _render_csv(self)

    @property
    def content_sha256(self) -> str:
        """SHA-256 of the canonical CSV text (UTF-8): the data, not where it came from."""
        return hashlib.sha256(self._canonical_csv.encode("utf-8")).hexdigest()

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Dataset):
            return NotImplemented
        return self._canonical_csv == other._canonical_csv

    def __hash__(self) -> int:
        return hash(self._canonical_csv)

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickle by value (e.g. to a worker process); the copy is validated again on arrival and
        keeps the canonical CSV text when it was rendered (its hash needs no second rendering)."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        values["extra"] = dict(self.extra)
        return (_rebuild, (values, self.__dict__.get("_canonical_csv")))

    def renamed(self, source: str) -> Dataset:
        """The same content under the name ``source``, its rows numbered as in its canonical CSV
        (header row 1): the data set as a reader of that text would give it, the rendered text kept."""
        out = dataclasses.replace(self, source=source, row_numbers=np.zeros(0, np.int64), row_label="row")
        if "_canonical_csv" in self.__dict__:
            out.__dict__["_canonical_csv"] = self.__dict__["_canonical_csv"]
        return out

    def _text_columns(self) -> list[tuple[str, Sequence[str]]]:
        """(name, cells) for every column written, in the stable order of the spec's table."""
        out: list[tuple[str, Sequence[str]]] = []

        def numbers(names: Sequence[str], array: NDArray[Any] | None) -> None:
            if array is None:
                return
            matrix = array.reshape(len(array), -1)
            for k, name in enumerate(names):
                out.append((name, [repr(float(v)) for v in matrix[:, k]]))

        numbers(AXIS_COLUMNS, self.a_deg)
        numbers(XYZ_COLUMNS, self.xyz_mm)
        if self.more_xyz_mm is not None:
            for k in range(self.more_xyz_mm.shape[1]):
                numbers(reflector_columns(k + 2), self.more_xyz_mm[:, k, :])
        if self.dir is not None:
            for k, name in enumerate(DIR_COLUMNS):
                out.append((name, [str(int(v)) for v in self.dir[:, k]]))
        if self.g_deg is not None:
            for k, name in enumerate(GRATING_COLUMNS):
                if self.g_present[k]:
                    numbers((name,), self.g_deg[:, k])
        if self.payload_kg.any():
            numbers(("payload_kg",), self.payload_kg)
        numbers(("temp_c",), self.temp_c)
        numbers(("t_s",), self.t_s)
        if self.split is not None:
            out.append(("split", [str(s) for s in self.split]))
        if self.repeat is not None:
            out.append(("repeat", [str(int(v)) for v in self.repeat]))
        if self.pose_id is not None:
            out.append(("pose_id", list(self.pose_id)))
        if self.station is not None:
            out.append(("station", list(self.station)))
        numbers(QUATERNION_COLUMNS, self.probe_q_wxyz)
        numbers(("sigma_mm",), self.sigma_mm)
        numbers(TARGET_XYZ_COLUMNS, self.target_xyz_mm)
        numbers(TARGET_ABC_COLUMNS, self.target_abc_deg)
        out.extend(self.extra.items())
        return out

    # ---- rows ----------------------------------------------------------------------------------
    def fit_rows(self) -> IntArray:
        """Indices of rows marked ``fit``; every row when there is no ``split`` column."""
        if self.split is None:
            return np.arange(len(self))
        return np.flatnonzero(self.split == "fit")

    def check_rows(self) -> IntArray:
        """Indices of rows marked ``check``; none when there is no ``split`` column."""
        if self.split is None:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self.split == "check")

    def subset(self, idx: ArrayLike) -> Dataset:
        """The rows ``idx`` (integer indices or a boolean mask of length n), same source."""
        index = np.asarray(idx)
        if index.dtype == bool:
            if index.shape != (len(self),):
                raise ValueError(f"subset: boolean mask of length {len(self)} expected, got {index.shape}")
            index = np.flatnonzero(index)
        index = index.astype(np.int64).reshape(-1)

        def take(array: NDArray[Any] | None) -> NDArray[Any] | None:
            return None if array is None else array[index]

        def take_text(values: Sequence[str]) -> tuple[str, ...]:
            return tuple(values[int(i)] for i in index)

        return Dataset(
            a_deg=take(self.a_deg),
            xyz_mm=take(self.xyz_mm),
            dir=take(self.dir),
            g_deg=take(self.g_deg),
            g_present=self.g_present,
            payload_kg=self.payload_kg[index],
            temp_c=take(self.temp_c),
            t_s=take(self.t_s),
            split=take(self.split),
            repeat=take(self.repeat),
            pose_id=None if self.pose_id is None else take_text(self.pose_id),
            station=None if self.station is None else take_text(self.station),
            probe_q_wxyz=take(self.probe_q_wxyz),
            sigma_mm=take(self.sigma_mm),
            target_xyz_mm=take(self.target_xyz_mm),
            target_abc_deg=take(self.target_abc_deg),
            more_xyz_mm=take(self.more_xyz_mm),
            extra={k: take_text(v) for k, v in self.extra.items()},
            source=self.source,
            row_numbers=self.row_numbers[index],
            row_label=self.row_label,
        )

    def with_split(self, labels: Sequence[str] | NDArray[np.str_]) -> Dataset:
        """A copy with the ``split`` column set to ``labels`` ('fit' / 'check' per row)."""
        return dataclasses.replace(self, split=np.asarray(labels))

    def split_or_draw(
        self, *, seed: int = DEFAULT_SPLIT_SEED, check_fraction: float = DEFAULT_CHECK_FRACTION
    ) -> SplitChoice:
        """Fit and check rows: the ``split`` column if there is one, else a reproducible draw.

        The draw holds out ``round(check_fraction * groups)`` groups of rows (at least one, and at
        least one group is left to fit when there are two or more), chosen by
        ``numpy.random.default_rng(seed)``. A group is one ``pose_id``, or, without it, one set of
        identical axis values (identical target positions for pose targets), so repeated
        measurements of a pose never land on both sides. The same data and seed give the same rows.
        """
        if not 0.0 < check_fraction < 1.0:
            raise ValueError(f"check_fraction must be between 0 and 1 (exclusive), got {check_fraction}")
        n = len(self)
        if self.split is not None:
            fit, check = self.fit_rows(), self.check_rows()
            message = f"{self.source}: split column gives {len(fit)} fit and {len(check)} check rows"
            return SplitChoice(fit, check, drawn=False, seed=None, message=message)
        if self.pose_id is not None:
            _, group = np.unique(np.asarray(self.pose_id, dtype=str), return_inverse=True)
        else:
            keys = self.a_deg if self.a_deg is not None else self.target_xyz_mm
            assert keys is not None
            _, group = np.unique(keys, axis=0, return_inverse=True)
        group = np.asarray(group).reshape(-1)
        n_groups = int(group.max()) + 1 if n else 0
        n_check = min(max(round(check_fraction * n_groups), 1), n_groups - 1) if n_groups >= 2 else 0
        chosen = np.random.default_rng(seed).choice(n_groups, size=n_check, replace=False)
        is_check = np.isin(group, chosen)
        fit, check = np.flatnonzero(~is_check), np.flatnonzero(is_check)
        held = _describe_numbers(self.row_numbers[check])
        message = (
            f"{self.source}: no split column; held out {len(check)} of {n} {self.row_label}s as check "
            f"rows, drawn with seed {seed} (check fraction {check_fraction:g}): "
            f"{self.row_label}s {held or 'none'}"
        )
        if n_groups < n:
            by = "pose_id" if self.pose_id is not None else "identical axis values"
            message += (
                f" (drawn by pose: {n} rows are {n_groups} poses by {by}; a pose's repeats stay together)"
            )
        return SplitChoice(fit, check, drawn=True, seed=seed, message=message)

    # ---- summary -------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """A JSON-ready description: rows, columns, split counts, payloads, ranges."""

        def ranges(names: Sequence[str], array: NDArray[Any] | None) -> dict[str, list[float]] | None:
            if array is None or not len(array):
                return None
            matrix = array.reshape(len(array), -1)
            return {
                name: [float(np.min(matrix[:, k])), float(np.max(matrix[:, k]))]
                for k, name in enumerate(names)
            }

        split: dict[str, Any]
        if self.split is None:
            split = {"column": False, "fit": None, "check": None}
        else:
            split = {"column": True, "fit": len(self.fit_rows()), "check": len(self.check_rows())}
        return {
            "source": self.source,
            "rows": len(self),
            "columns": list(self.columns),
            "extra_columns": list(self.extra),
            "axes": self.a_deg is not None,
            "measured_xyz": self.xyz_mm is not None,
            "reflectors": self.n_reflectors,
            "pose_targets": self.target_xyz_mm is not None,
            "split": split,
            "payloads_kg": sorted({float(p) for p in self.payload_kg}),
            "dir": self.dir is not None,
            "gratings": [name for name, p in zip(GRATING_COLUMNS, self.g_present, strict=True) if p],
            "repeat": self.repeat is not None,
            "pose_id": self.pose_id is not None,
            "stations": None if self.station is None else dict(sorted(Counter(self.station).items())),
            "probe_orientation": self.probe_q_wxyz is not None,
            "sigma_mm": None
            if self.sigma_mm is None
            else {
                "min": float(np.min(self.sigma_mm)),
                "median": float(np.median(self.sigma_mm)),
                "max": float(np.max(self.sigma_mm)),
            },
            "axis_range_deg": ranges(AXIS_COLUMNS, self.a_deg),
            "xyz_range_mm": ranges(XYZ_COLUMNS, self.xyz_mm),
            "target_range_mm": ranges(TARGET_XYZ_COLUMNS, self.target_xyz_mm),
            "temp_range_c": ranges(("temp_c",), self.temp_c),
            "content_sha256": self.content_sha256,
        }


def _rebuild(values: dict[str, Any], canonical_csv: str | None = None) -> Dataset:
    dataset = Dataset(**values)
    if canonical_csv is not None:  # the content it was rendered from: the same arrays, the same text
        dataset.__dict__["_canonical_csv"] = canonical_csv
    return dataset


@dataclass(frozen=True)
class SplitChoice:
    """Which rows fit a model and which are held out to judge it, and how that was decided."""

    fit_rows: IntArray
    check_rows: IntArray
    drawn: bool
    seed: int | None
    message: str

    def labels(self, n: int | None = None) -> NDArray[np.str_]:
        """Per-row 'fit' / 'check' labels (for :meth:`Dataset.with_split`)."""
        size = len(self.fit_rows) + len(self.check_rows) if n is None else n
        out = np.full(size, "fit", dtype="<U5")
        out[self.check_rows] = "check"
        return out


def _describe_numbers(numbers: Iterable[int]) -> str:
    """``2-4, 7, 9-10`` for 2, 3, 4, 7, 9, 10."""
    parts: list[str] = []
    run: list[int] = []
    for value in sorted(int(v) for v in numbers):
        if run and value == run[-1] + 1:
            run.append(value)
            continue
        if run:
            parts.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
        run = [value]
    if run:
        parts.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
    return ", ".join(parts)


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------
def dataset_to_csv(dataset: Dataset) -> str:
    """The data set as CSV text: header, then one line per row; floats as ``repr`` (exact round trip).

    Rendered once per data set and kept (its hash, its columns and the stored text are the same text).
    """
    return dataset._canonical_csv


def _render_csv(dataset: Dataset) -> str:
    columns = dataset._text_columns()
    lines = [",".join(_quote(name) for name, _ in columns)]
    cells = [
        [_quote(c) for c in column] if _NEEDS_QUOTES.search("".join(column)) else column
        for _, column in columns
    ]  # one search per column: numeric columns (most of them) never need quotes
    lines.extend(map(",".join, zip(*cells, strict=True)))
    return "\n".join(lines) + "\n"


_NEEDS_QUOTES = re.compile('[,"\r\n]')


def _quote(cell: str) -> str:
    """A CSV cell (RFC 4180): quoted when it holds a comma, a quote or a line break."""
    return '"' + cell.replace('"', '""') + '"' if _NEEDS_QUOTES.search(cell) else cell


def write_dataset(dataset: Dataset, dest: str | os.PathLike[str] | TextIO) -> None:
    """Write ``dataset`` as CSV to a path (atomically: a temporary file renamed) or an open text file."""
    text = dataset_to_csv(dataset)
    if isinstance(dest, str | os.PathLike):
        write_text_atomic(dest, text)
        return
    dest.write(text)
