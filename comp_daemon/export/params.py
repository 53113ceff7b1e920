"""A kinematic model's identified parameters in listing units (mm, deg), and the CSV listing.

:class:`ControllerParams` holds what every parameter listing says; :func:`controller_params` makes
it from a :class:`~comp_daemon.models.kinematic.KinematicModel` (with its effects and its
covariance's 1-σ), :func:`model_of` makes the model back from it. The makers' listings are in
:mod:`~comp_daemon.export.krl` (KUKA) and :mod:`~comp_daemon.export.rapid` (ABB);
the CSV one is here (:func:`format_csv` / :func:`parse_csv`): ``# key: value`` header lines, then
``name, nominal, identified, delta, unit, sigma``, one parameter a row (sigma empty for a parameter
the fit did not identify). Text in, values out; numbers as the shortest decimal that reads back to
the same double, so a listing read back compensates as the model it came from.

Parameters (per axis j = 1..6; conventions of :mod:`comp_daemon.kinematics.params`,
``T_{j-1,j} = Rz(theta_j)·Tz(d_j)·Tx(a_j)·Rx(alpha_j)·Ry(beta_j)``, ``theta_j = sign_j·A_j +
offset_j``): ``a`` (mm), ``alpha`` (deg), ``d`` (mm), ``theta`` (the zero offset, deg), ``beta``
(deg), ``sign`` (1 or −1, of the robot description, not identified). Frames: ``base`` is the
kinematic chain's root (the frame joint 1 turns in) in the robot base frame, identity on the
nominal robot; ``registration`` the robot base frame in the measurement frame (identity when the
data were measured in the robot base frame; else the tracker's frame, for information — the
controller does not use it); ``tool`` the TCP in the flange frame (mm). In the CSV a frame is
``x, y, z`` (mm) and ``rx, ry, rz``, its rotation vector (axis × angle, deg). Non-geometric
effects (``kinematic+ratio+backlash`` …) by their catalogue names and units
(:mod:`comp_daemon.models.effects.catalogue`), with ``n_harmonics`` and ``t_ref_c`` (°C).
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.export.frames import (
    frame,
    matrix_to_rotvec_deg,
    num,
    rigid_inverse,
    rotvec_deg_to_matrix,
)
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.kinematics.so3 import skew
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.covariance import ParameterCovariance
from comp_daemon.models.effects import EffectParams
from comp_daemon.models.effects.params import parse_param_name
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "CSV_COLUMNS",
    "FRAME_AXES",
    "JOINT_FIELDS",
    "ControllerParams",
    "ListingInfo",
    "controller_params",
    "effect_meaning",
    "effect_unit",
    "format_csv",
    "header_pairs",
    "listing_of",
    "listing_table",
    "model_of",
    "of_rows",
    "parse_csv",
    "rows_of",
    "sigma_note",
    "with_frames",
]

#: per-axis fields in listing order, with their units
JOINT_FIELDS: tuple[tuple[str, str], ...] = (
    ("a", "mm"),
    ("alpha", "deg"),
    ("d", "mm"),
    ("theta", "deg"),
    ("beta", "deg"),
)
# column of each field in KinematicParams.joint_table() (theta, d, a, alpha, beta), angles in rad
_TABLE_COLUMN = {"theta": 0, "d": 1, "a": 2, "alpha": 3, "beta": 4}
FRAME_AXES = ("x", "y", "z", "rx", "ry", "rz")
FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ListingInfo:
    """The header of a listing: which robot and model, when fitted, how well it fits."""

    robot: str
    model: str
    model_id: str
    fit_date: str
    fit_rms_mm: float | None = None
    check_rms_mm: float | None = None

    def lines(self) -> list[str]:
        def mm(v: float | None) -> str:
            return "not measured" if v is None else f"{num(v)} mm"

        return [
            f"robot: {self.robot}",
            f"model: {self.model}",
            f"model id: {self.model_id}",
            f"fit date: {self.fit_date}",
            f"fit RMS: {mm(self.fit_rms_mm)}",
            f"check RMS: {mm(self.check_rms_mm)}",
        ]

    @classmethod
    def of_lines(cls, pairs: Mapping[str, str]) -> ListingInfo:
        def mm(key: str) -> float | None:
            text = pairs.get(key, "not measured").strip()
            return None if text == "not measured" else float(text.removesuffix("mm").strip())

        return cls(
            robot=pairs.get("robot", ""),
            model=pairs.get("model", ""),
            model_id=pairs.get("model id", ""),
            fit_date=pairs.get("fit date", ""),
            fit_rms_mm=mm("fit RMS"),
            check_rms_mm=mm("check RMS"),
        )


@dataclass(frozen=True, slots=True)
class ControllerParams:
    """A kinematic model's parameters in listing units (module docstring); tables are (6, 5) in the
    order of :data:`JOINT_FIELDS`."""

    info: ListingInfo
    nominal: FloatArray  # (6, 5) a mm, alpha deg, d mm, theta offset deg, beta deg
    identified: FloatArray  # (6, 5)
    sign: FloatArray  # (6,)
    tool_nominal_mm: FloatArray  # (3,) TCP in the flange frame (z out of the flange)
    tool_mm: FloatArray  # (3,)
    base_T_root: FloatArray  # (4, 4) chain root in the robot base frame
    meas_T_base: FloatArray  # (4, 4) robot base frame in the measurement frame
    effects: dict[str, float] | None = None  # name -> value (catalogue units); None: no effects
    n_harmonics: int = 0
    t_ref_c: float = 20.0
    sigma: dict[str, float] = field(default_factory=dict)  # row name -> 1-sigma (listing units)


def listing_table(params: KinematicParams) -> FloatArray:
    table = params.joint_table()
    cols = [table[:, _TABLE_COLUMN[name]] for name, _ in JOINT_FIELDS]
    return np.stack(
        [np.degrees(c) if unit == "deg" else c for c, (_, unit) in zip(cols, JOINT_FIELDS, strict=True)],
        axis=1,
    )


def _kinematic_table(listing: FloatArray) -> FloatArray:
    """(6, 5) table of KinematicParams.joint_table (rad, mm) from a listing table (deg, mm)."""
    out = np.empty((6, 5))
    for k, (name, unit) in enumerate(JOINT_FIELDS):
        out[:, _TABLE_COLUMN[name]] = np.radians(listing[:, k]) if unit == "deg" else listing[:, k]
    return out


def controller_params(model: KinematicModel, info: ListingInfo) -> ControllerParams:
    """The listing values of a kinematic model (with its effects and, where it has one, the 1-σ of
    every identified parameter from its covariance)."""
    params = model.params
    nominal = KinematicParams.from_robot(model.robot)
    reg = np.array(model.registration, dtype=float)
    effects = None
    if model.effects is not None:
        names = model.effects.names()
        values = model.effects.get(names)
        cov = _covariance(model)
        fitted = set(cov.names) if cov is not None else set()
        effects = {n: float(v) for n, v in zip(names, values, strict=True) if v != 0.0 or n in fitted}
    return ControllerParams(
        info=info,
        nominal=listing_table(nominal),
        identified=listing_table(params),
        sign=np.array(params.sign, dtype=float),
        tool_nominal_mm=np.array(nominal.tool_xyz_mm, dtype=float),
        tool_mm=np.array(params.tool_xyz_mm, dtype=float),
        base_T_root=rigid_inverse(reg) @ params.world_T_base,
        meas_T_base=reg,
        effects=effects,
        n_harmonics=0 if model.effects is None else model.effects.n_harmonics,
        t_ref_c=20.0 if model.effects is None else float(model.effects.t_ref_c),
        sigma=_sigma(model, reg),
    )


def listing_of(
    model: ErrorModel, document: Mapping[str, Any], check_rms_mm: float | None = None
) -> ControllerParams:
    """The listing of a model loaded from its artifact ``document`` (the header from the document:
    the fitted model's name, the first 16 hex digits of its checksum as the id, its date, the fit
    RMS); ValueError for a model that is not kinematic."""
    if not isinstance(model, KinematicModel):
        raise ValueError(
            f"a {model.kind} model has no kinematic parameters to list "
            "(parameter listings are of kinematic models; target lists take every kind)"
        )
    fit = document.get("fit") or {}
    rms = fit.get("rms_mm")
    info = ListingInfo(
        robot=model.robot.name,
        model=str(fit.get("model", model.kind)),
        model_id=str(document.get("checksum_sha256", ""))[:16],
        fit_date=str(document.get("created_utc", "")),
        fit_rms_mm=float(rms) if isinstance(rms, int | float) else None,
        check_rms_mm=check_rms_mm,
    )
    return controller_params(model, info)


def _covariance(model: KinematicModel) -> ParameterCovariance | None:
    return model.uncertainty if isinstance(model.uncertainty, ParameterCovariance) else None


def _sigma(model: KinematicModel, reg: FloatArray) -> dict[str, float]:
    """1-σ per listing row from the model's covariance (angles in deg; the base frame's increments,
    identified in the measurement frame, mapped into the robot base frame to first order)."""
    cov = _covariance(model)
    if cov is None:
        return {}
    std = np.sqrt(np.maximum(np.diag(cov.covariance), 0.0))
    out: dict[str, float] = {}
    for name, s in zip(cov.names, std, strict=True):
        m = re.fullmatch(r"(theta|alpha|beta)([1-6])", name)
        if m or name.startswith("base_"):
            if m:
                out[name] = float(np.degrees(s))
            continue
        out[name] = float(s)
    base = [f"base_{a}" for a in FRAME_AXES]
    if any(b in cov.names for b in base):
        index = {n: i for i, n in enumerate(cov.names)}
        sub = np.zeros((6, 6))
        idx = [index.get(b) for b in base]
        for r, i in enumerate(idx):
            for c, j in enumerate(idx):
                if i is not None and j is not None:
                    sub[r, c] = cov.covariance[i, j]
        rot_t = reg[:3, :3].T
        lin = np.zeros((6, 6))  # base_T_root = reg⁻¹·Δ·reg with Δ the identified increment
        lin[:3, :3] = rot_t
        lin[:3, 3:] = -rot_t @ skew(reg[:3, 3])
        lin[3:, 3:] = rot_t
        s6 = np.sqrt(np.maximum(np.diag(lin @ sub @ lin.T), 0.0))
        s6[3:] = np.degrees(s6[3:])
        out.update({b: float(v) for b, v in zip(base, s6, strict=True)})
    return out


def model_of(listing: ControllerParams, robot: RobotDescription) -> KinematicModel:
    """The kinematic model a listing describes, on ``robot`` (whose nominal values and signs must
    be the listing's; ValueError otherwise)."""
    nominal = KinematicParams.from_robot(robot)
    if not np.allclose(listing_table(nominal), listing.nominal, rtol=0.0, atol=1e-9) or not np.array_equal(
        nominal.sign, listing.sign
    ):
        raise ValueError(f"the listing's nominal parameters are not those of robot '{robot.name}'")
    table = _kinematic_table(listing.identified)
    reg = np.array(listing.meas_T_base, dtype=float)
    params = replace(
        nominal.with_joint_table(table),
        tool_xyz_mm=np.array(listing.tool_mm, dtype=float),
        world_T_base=reg @ listing.base_T_root,
    )
    effects = None
    if listing.effects is not None:
        names = list(listing.effects)
        effects = EffectParams.zeros(listing.n_harmonics, listing.t_ref_c).with_values(
            names, np.array([listing.effects[n] for n in names])
        )
    return KinematicModel(robot, params, effects, reg)


# ------------------------------------------------------------------------------------------ rows
def rows_of(listing: ControllerParams) -> list[tuple[str, float, float, str]]:
    """(name, nominal, identified, unit) of every parameter, in listing order."""
    rows: list[tuple[str, float, float, str]] = []
    for j in range(6):
        for k, (name, unit) in enumerate(JOINT_FIELDS):
            rows.append((f"{name}{j + 1}", listing.nominal[j, k], listing.identified[j, k], unit))
    rows += [(f"sign{j + 1}", listing.sign[j], listing.sign[j], "1") for j in range(6)]
    rows += [(f"tool_{a}", listing.tool_nominal_mm[i], listing.tool_mm[i], "mm") for i, a in enumerate("xyz")]
    for stem, t in (("base", listing.base_T_root), ("registration", listing.meas_T_base)):
        values = [*t[:3, 3], *matrix_to_rotvec_deg(t[:3, :3])]
        nominal = np.zeros(6) if stem == "base" else values
        rows += [
            (f"{stem}_{a}", nominal[i], values[i], "mm" if i < 3 else "deg") for i, a in enumerate(FRAME_AXES)
        ]
    if listing.effects is not None:
        rows.append(("n_harmonics", listing.n_harmonics, listing.n_harmonics, "1"))
        rows.append(("t_ref_c", listing.t_ref_c, listing.t_ref_c, "degC"))
        rows += [(n, 0.0, v, effect_unit(n, listing.n_harmonics)) for n, v in listing.effects.items()]
    return rows


def effect_unit(name: str, n_harmonics: int) -> str:
    ref = parse_param_name(name, n_harmonics)
    return ref.effect.arrays[ref.array].unit


def effect_meaning(name: str, n_harmonics: int) -> str:
    ref = parse_param_name(name, n_harmonics)
    return ref.effect.arrays[ref.array].meaning


def of_rows(info: ListingInfo, rows: Mapping[str, tuple[float, float]], where: str) -> ControllerParams:
    """A listing from (nominal, identified) by row name (the names of :func:`rows_of`)."""

    def get(name: str, column: int = 1) -> float:
        if name not in rows:
            raise ValueError(f"{where}: no value for '{name}'")
        return rows[name][column]

    nominal = np.array([[get(f"{n}{j}", 0) for n, _ in JOINT_FIELDS] for j in range(1, 7)])
    identified = np.array([[get(f"{n}{j}") for n, _ in JOINT_FIELDS] for j in range(1, 7)])
    frames = []
    for stem in ("base", "registration"):
        v = [get(f"{stem}_{a}") for a in FRAME_AXES]
        frames.append(frame(np.array(v[:3]), rotvec_deg_to_matrix(np.array(v[3:]))))
    fixed = {
        "n_harmonics",
        "t_ref_c",
        *(n for n in rows if re.fullmatch(r"(a|alpha|d|theta|beta|sign)[1-6]", n)),
    }
    fixed |= {f"{s}_{a}" for s in ("tool", "base", "registration") for a in FRAME_AXES}
    effects = {n: v for n, (_, v) in rows.items() if n not in fixed} if "n_harmonics" in rows else None
    return ControllerParams(
        info=info,
        nominal=nominal,
        identified=identified,
        sign=np.array([get(f"sign{j}") for j in range(1, 7)]),
        tool_nominal_mm=np.array([get(f"tool_{a}", 0) for a in "xyz"]),
        tool_mm=np.array([get(f"tool_{a}") for a in "xyz"]),
        base_T_root=frames[0],
        meas_T_base=frames[1],
        effects=effects,
        n_harmonics=int(get("n_harmonics")) if effects is not None else 0,
        t_ref_c=get("t_ref_c") if effects is not None else 20.0,
    )


# ------------------------------------------------------------------------------------------- csv
CSV_COLUMNS = ("name", "nominal", "identified", "delta", "unit", "sigma")


def format_csv(listing: ControllerParams) -> str:
    """The CSV listing: ``# key: value`` header lines, then :data:`CSV_COLUMNS` (sigma empty for a
    parameter the fit did not identify)."""
    out = io.StringIO()
    out.write("# comp-daemon identified kinematic parameters (lengths mm, angles deg)\n")
    out.writelines(f"# {line}\n" for line in listing.info.lines())
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for name, nom, ident, unit in rows_of(listing):
        sigma = listing.sigma.get(name)
        writer.writerow(
            [name, num(nom), num(ident), num(ident - nom), unit, "" if sigma is None else num(sigma)]
        )
    return out.getvalue()


def parse_csv(text: str, where: str = "<csv>") -> ControllerParams:
    lines = text.splitlines()
    header = dict(header_pairs(line[1:] for line in lines if line.startswith("#")))
    body = [line for line in lines if line.strip() and not line.startswith("#")]
    reader = csv.DictReader(body)
    if tuple(reader.fieldnames or ()) != CSV_COLUMNS:
        raise ValueError(f"{where}: expected the columns {', '.join(CSV_COLUMNS)}")
    rows: dict[str, tuple[float, float]] = {}
    sigma: dict[str, float] = {}
    for row in reader:
        rows[row["name"]] = (float(row["nominal"]), float(row["identified"]))
        if row["sigma"]:
            sigma[row["name"]] = float(row["sigma"])
    listing = of_rows(ListingInfo.of_lines(header), rows, where)
    return _with_sigma(listing, sigma)


def _with_sigma(listing: ControllerParams, sigma: dict[str, float]) -> ControllerParams:
    return replace(listing, sigma=sigma)


def header_pairs(lines: Iterable[str]) -> list[tuple[str, str]]:
    out = []
    for line in lines:
        key, sep, value = line.partition(":")
        if sep:
            out.append((key.strip(), value.strip()))
    return out


def sigma_note(listing: ControllerParams, name: str) -> str:
    s = listing.sigma.get(name)
    return "" if s is None else f" (1-sigma {s:.3g})"


def with_frames(listing: ControllerParams, base: FloatArray, registration: FloatArray) -> ControllerParams:
    """``listing`` with its frames as the listing wrote them (not through rotation vectors)."""
    return replace(listing, base_T_root=base, meas_T_base=registration)
