"""How a file from another tool is read: field separator, decimal comma, length and angle units.

Spreadsheet and tracker-software exporters write ``;``-separated files with decimal commas
(``12,5``), positions in metres and angles in radians. comp-daemon reads them only when told
(:class:`ReadOptions`, the commands' ``--delimiter``, ``--decimal-comma`` and ``--units``), never by
guess; a file that looks as if it needed one of these options and was read without it is refused
with a message that names the option:

- a header row that is one column holding ``;`` (or tabs): ``--delimiter ';'`` (``--decimal-comma``
  when the numbers have decimal commas) (:mod:`comp_daemon.data.cells`);
- a number with a decimal comma (``12,5``, in a quoted or ``;``-separated cell): ``--decimal-comma``
  (:mod:`comp_daemon.data.cells`);
- positions that spread a thousand times less than the nominal robot's at the same axis values:
  ``--units m,deg`` (the fit's and diagnosis's scale check,
  :func:`comp_daemon.estimation.registration.scale_problem`, which knows the robot);
- axis values ``a1 … a6`` all within ±2π while one axis spans more than :data:`MIN_SPREAD`:
  ``--units mm,rad`` (here).

Stating ``--units`` (even ``mm,deg``) turns the radian refusal off: the user has said what the
numbers are.

``--decimal-comma`` reads ``,`` as the decimal mark and, unless ``--delimiter`` says otherwise,
``;`` as the field separator; a ``.`` in a number is then refused (a thousands separator would
read as a decimal point). ``--units LENGTH,ANGLE`` (``mm`` or ``m``; ``deg`` or ``rad``) scales the
length columns (``x, y, z``, ``xK, yK, zK``, ``tx, ty, tz``, ``sigma_mm``) and the angle columns
(``a1 … a6``, ``g1 … g6``, ``ta, tb, tc``) to mm and degrees before every other check, so limits,
refusals and everything downstream see the data set's own units; in a ballbar or cross-bar campaign
also its lengths (``bar_mm``, ``bar_nominal_mm``, ``cx, cy, cz``, ``bar_l_mm``; ``dr_um`` stays µm,
and ``--decimal-comma`` reads ``dr_um``, ``arc`` and ``placement`` too). Cells that are not plain numbers
are left as they are, for the reader to refuse them.

``--euler CONVENTION`` reads a 6-DOF probe's orientation from the Euler angle columns ``e1, e2,
e3`` in the stated convention and turns them into ``qw, qx, qy, qz`` (:mod:`comp_daemon.data.euler`);
a file with ``e1, e2, e3`` beside ``x, y, z`` read without it is refused naming the option.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from comp_daemon.data.cells import CellTable
from comp_daemon.data.columns import (
    ANGLE_COLUMNS,
    LENGTH_COLUMNS,
    QUATERNION_COLUMNS,
    DatasetError,
    is_numeric_column,
    is_reflector_column,
)
from comp_daemon.data.euler import EULER_COLUMNS, EulerConvention, parse_euler
from comp_daemon.data.table import Dataset

__all__ = [
    "CAMPAIGN_LENGTH_COLUMNS",
    "CAMPAIGN_MARKERS",
    "CAMPAIGN_NUMBER_COLUMNS",
    "DELIMITERS",
    "MIN_SPREAD",
    "ReadOptions",
    "parse_units",
]

#: the field separators a reader takes, by their names on the command line
DELIMITERS = {",": ",", ";": ";", "tab": "\t"}
#: the spread (largest max − min of an axis column) above which a file is a campaign, not one pose
MIN_SPREAD = 0.2
#: the length columns of a ballbar or cross-bar campaign (:mod:`comp_daemon.data.bars`), scaled by
#: ``--units`` and read with ``--decimal-comma`` in a file that has one of :data:`CAMPAIGN_MARKERS`
CAMPAIGN_LENGTH_COLUMNS: tuple[str, ...] = ("bar_mm", "bar_nominal_mm", "cx", "cy", "cz", "bar_l_mm")
#: their further number columns: read with ``--decimal-comma``, never scaled (``dr_um`` is µm by name)
CAMPAIGN_NUMBER_COLUMNS: tuple[str, ...] = ("dr_um", "arc", "placement")
#: the columns that make a file a ballbar or cross-bar campaign
CAMPAIGN_MARKERS: tuple[str, ...] = ("bar_mm", "bar_nominal_mm", "dr_um", "placement", "socket", "bar_l_mm")

LengthUnit = Literal["mm", "m"]
AngleUnit = Literal["deg", "rad"]
_LENGTH_SCALE = {"mm": 1.0, "m": 1000.0}
_ANGLE_SCALE = {"deg": 1.0, "rad": 180.0 / math.pi}

_PLAIN = re.compile(r"\s*[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\s*", re.ASCII)
_COMMA_NUMBER = re.compile(r"\s*[+-]?(?:\d+(?:,\d*)?|,\d+)(?:[eE][+-]?\d+)?\s*", re.ASCII)


def parse_units(text: str) -> tuple[LengthUnit, AngleUnit]:
    """``"m,rad"`` → ``("m", "rad")``: a length unit (mm, m) and an angle unit (deg, rad), in either
    order; ValueError naming what is wrong."""
    parts = [p.strip().lower() for p in text.split(",")]
    lengths = [p for p in parts if p in _LENGTH_SCALE]
    angles = [p for p in parts if p in _ANGLE_SCALE]
    unknown = [p for p in parts if p not in _LENGTH_SCALE and p not in _ANGLE_SCALE]
    if unknown or len(parts) != 2 or len(lengths) != 1 or len(angles) != 1:
        raise ValueError(
            f"--units {text!r}: expected a length unit (mm or m) and an angle unit (deg or rad), e.g. 'm,rad'"
        )
    length: LengthUnit = "m" if lengths[0] == "m" else "mm"
    angle: AngleUnit = "rad" if angles[0] == "rad" else "deg"
    return length, angle


def _numeric(name: str) -> bool:
    return is_numeric_column(name)


def _length_column(name: str) -> bool:
    return name in LENGTH_COLUMNS or is_reflector_column(name)


def _angle_column(name: str) -> bool:
    return name in ANGLE_COLUMNS


@dataclass(frozen=True, slots=True)
class ReadOptions:
    """How to read a file (module docstring). The default reads the data set format as specified:
    ``,``-separated, ``.`` decimals, mm and degrees."""

    delimiter: str = ","
    decimal_comma: bool = False
    length_unit: LengthUnit = "mm"
    angle_unit: AngleUnit = "deg"
    units_stated: bool = False  # --units was given: no guessing refusal on the units
    euler: EulerConvention | None = None  # --euler: e1, e2, e3 are a probe's orientation

    def __post_init__(self) -> None:
        if self.delimiter not in DELIMITERS.values():
            raise ValueError(f"field separator {self.delimiter!r}: expected one of ',', ';', tab")
        if self.decimal_comma and self.delimiter == ",":
            raise ValueError("--decimal-comma with ',' as the field separator: choose --delimiter ';' or tab")

    @classmethod
    def of(
        cls,
        delimiter: str | None = None,
        decimal_comma: bool = False,
        units: str | None = None,
        euler: str | None = None,
    ) -> ReadOptions:
        """The options as the command line states them (``delimiter`` by name: ``,``, ``;``, ``tab``;
        ``euler`` a convention, :func:`comp_daemon.data.euler.parse_euler`)."""
        if delimiter is not None and delimiter not in DELIMITERS:
            raise ValueError(f"--delimiter {delimiter!r}: expected one of {', '.join(map(repr, DELIMITERS))}")
        sep = DELIMITERS[delimiter] if delimiter is not None else (";" if decimal_comma else ",")
        out = cls(delimiter=sep, decimal_comma=decimal_comma)
        if units is not None:
            length, angle = parse_units(units)
            out = replace(out, length_unit=length, angle_unit=angle, units_stated=True)
        if euler is not None:
            out = replace(out, euler=parse_euler(euler))
        return out

    @property
    def is_default(self) -> bool:
        return self == ReadOptions()

    def describe(self) -> str:
        """A short statement of how the file was read (for summaries)."""
        sep = {",": "','", ";": "';'", "\t": "tab"}[self.delimiter]
        mark = "','" if self.decimal_comma else "'.'"
        units = f"lengths in {self.length_unit}, angles in {self.angle_unit}"
        euler = f", probe orientation from e1, e2, e3 ({self.euler.name})" if self.euler else ""
        return f"fields by {sep}, decimal mark {mark}, {units}{euler}"

    # ----------------------------------------------------------------------------------- cells
    def convert(self, table: CellTable) -> CellTable:
        """The table with decimal commas read, lengths and angles scaled to mm and degrees and Euler
        angles turned into quaternions."""
        length = _LENGTH_SCALE[self.length_unit]
        angle = _ANGLE_SCALE[self.angle_unit]
        euler = self._euler_columns(table)
        if not self.decimal_comma and length == 1.0 and angle == 1.0 and not euler:
            return table
        campaign = any(name in table.columns for name in CAMPAIGN_MARKERS)
        lengths = CAMPAIGN_LENGTH_COLUMNS if campaign else ()
        numbers = (*lengths, *CAMPAIGN_NUMBER_COLUMNS) if campaign else ()
        own = None if self.euler is None else self.euler.unit
        euler_scale = angle if own is None else _ANGLE_SCALE[own]
        columns = dict(table.columns)
        for name, cells in table.columns.items():
            if not (_numeric(name) or name in euler or name in numbers):
                continue
            out = list(cells)
            if self.decimal_comma:
                for i, cell in enumerate(out):
                    if "." in cell and _PLAIN.fullmatch(cell):
                        raise DatasetError(
                            f"{cell.strip()!r} has a '.', read with --decimal-comma (',' is the decimal "
                            "mark; a thousands separator is not allowed)",
                            source=table.source,
                            row=table.row_numbers[i],
                            column=name,
                            row_label=table.row_label,
                        )
                    if _COMMA_NUMBER.fullmatch(cell):
                        out[i] = cell.replace(",", ".")
            scale = euler_scale if name in euler else self._scale(name, length, angle, lengths)
            if scale != 1.0:
                out = [repr(float(c) * scale) if _PLAIN.fullmatch(c) else c for c in out]
            columns[name] = out
        converted = replace(table, columns=columns)
        return self._quaternions(converted) if euler else converted

    @staticmethod
    def _scale(name: str, length: float, angle: float, lengths: tuple[str, ...]) -> float:
        if _length_column(name) or name in lengths:
            return length
        return angle if _angle_column(name) else 1.0

    def _euler_columns(self, table: CellTable) -> tuple[str, ...]:
        """``e1, e2, e3`` when ``--euler`` reads them; a table the option does not fit is refused."""
        present = [c for c in EULER_COLUMNS if c in table.columns]

        def refuse(problem: str, column: str | None) -> DatasetError:
            return DatasetError(problem, source=table.source, row=1, column=column, row_label=table.row_label)

        if self.euler is None:
            if len(present) == len(EULER_COLUMNS) and "x" in table.columns:
                raise refuse(
                    "columns e1, e2, e3 beside x, y, z are read as a 6-DOF probe's Euler angles only in a "
                    "stated convention: read the file with --euler CONVENTION (e.g. --euler intrinsic-zyx)",
                    "e1",
                )
            return ()
        name = self.euler.name
        if len(present) != len(EULER_COLUMNS):
            missing = next(c for c in EULER_COLUMNS if c not in table.columns)
            raise refuse(f"column missing: --euler {name} reads the probe's angles from e1, e2, e3", missing)
        both = [c for c in QUATERNION_COLUMNS if c in table.columns]
        if both:
            raise refuse(
                f"the probe orientation is given twice, as {both[0]}.. and as e1, e2, e3 (--euler {name}); "
                "keep one",
                both[0],
            )
        return EULER_COLUMNS

    def _quaternions(self, table: CellTable) -> CellTable:
        """The table with ``e1, e2, e3`` (degrees by now) replaced by ``qw, qx, qy, qz``."""
        assert self.euler is not None
        n = len(table.row_numbers)
        e = np.zeros((n, 3))
        for k, name in enumerate(EULER_COLUMNS):
            for i, cell in enumerate(table.columns[name]):
                if not _PLAIN.fullmatch(cell):
                    raise DatasetError(
                        f"{cell.strip()!r} is not a number (an Euler angle of --euler {self.euler.name})",
                        source=table.source,
                        row=table.row_numbers[i],
                        column=name,
                        row_label=table.row_label,
                    )
                e[i, k] = float(cell)
        q = self.euler.quaternions(e)
        columns = {c: cells for c, cells in table.columns.items() if c not in EULER_COLUMNS}
        columns.update({c: [repr(float(v)) for v in q[:, k]] for k, c in enumerate(QUATERNION_COLUMNS)})
        at = sum(h not in EULER_COLUMNS for h in table.header[: table.header.index(EULER_COLUMNS[0])])
        rest = [h for h in table.header if h not in EULER_COLUMNS]
        header = [*rest[:at], *QUATERNION_COLUMNS, *rest[at:]]
        return replace(table, header=header, columns=columns)

    # ---------------------------------------------------------------------------------- values
    def check_units(self, data: Dataset) -> None:
        """Refuse a data set whose axis values look like radians read as degrees, unless ``--units``
        was stated."""
        if self.units_stated or len(data) < 3:
            return
        a = data.a_deg
        if a is not None and np.max(np.abs(a)) <= 2 * math.pi and np.max(np.ptp(a, axis=0)) > MIN_SPREAD:
            raise DatasetError(
                f"every axis value lies within ±2π (largest |value| {np.max(np.abs(a)):.4g}): angles in "
                "radians? Read the file with --units mm,rad (or m,rad); state --units mm,deg if they "
                "really are degrees",
                source=data.source,
                column="a1",
            )
