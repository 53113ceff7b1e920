"""KUKA listings: the identified parameters as a KRL data list, compensated targets as a ``.dat``.

Parameters (:func:`format_kuka` / :func:`parse_kuka`): ``DEFDAT CD_KINEMATICS``, per axis j an
``INT CD_SIGNj`` and two ``CD_MDH`` aggregates ``{A, ALPHA, D, THETA, BETA}`` (mm, deg; ``THETA``
the zero offset), ``CD_NOM_AXj`` (the robot description) and ``CD_AXj`` (identified); frames as
KUKA ``FRAME`` aggregates (``X, Y, Z`` mm; ``A, B, C`` deg, ``Rz(A)·Ry(B)·Rx(C)``): ``CD_BASE``
(the chain's root in the robot base frame), ``CD_REGISTRATION`` (the robot base frame in the
measurement frame), ``CD_NOM_TOOL`` / ``CD_TOOL`` (the TCP in KUKA's flange frame, x out of the
flange, as ``$TOOL``); effects as ``REAL CD_EFF_<name>`` with ``CD_HARMONICS`` and
``CD_T_REF_C``. The ``CD_`` names are comp-daemon's own, not KUKA system variables: the listing is
for review, not a machine-data file the controller loads.

Targets (:func:`format_krl_targets` / :func:`parse_krl_targets`): ``DEFDAT <module>``, per target
``E6AXIS XA_<name>`` (the compensated axis values, deg, for ``PTP``) and ``E6POS XP_<name>`` (the
nominal Cartesian target: ``X, Y, Z`` mm, ``A, B, C`` deg of KUKA's tool frame; without ``S``/``T``,
for reference: a ``LIN`` to it is not compensated). External axes ``E1..E6`` are 0.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np

from comp_daemon.export.frames import FloatArray, frame, matrix_to_rotvec_deg, num
from comp_daemon.export.params import (
    FRAME_AXES,
    JOINT_FIELDS,
    ControllerParams,
    ListingInfo,
    effect_meaning,
    effect_unit,
    header_pairs,
    of_rows,
    sigma_note,
    with_frames,
)
from comp_daemon.export.targets import TargetList, paired_names
from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix, flange_rotation_of_tool_abc, matrix_to_abc_deg
from comp_daemon.robot.description import FLANGE_R_KUKA_TOOL

__all__ = ["format_krl_targets", "format_kuka", "parse_krl_targets", "parse_kuka"]


# ------------------------------------------------------------------------------------------ kuka
_KRL_DECL = re.compile(r"^\s*DECL\s+(\w+)\s+(\w+)\s*=\s*(.+?)\s*$", re.IGNORECASE)
_KRL_FIELDS = {"a": "A", "alpha": "ALPHA", "d": "D", "theta": "THETA", "beta": "BETA"}


def _krl_aggregate(values: Mapping[str, float]) -> str:
    return "{" + ",".join(f"{k} {num(v)}" for k, v in values.items()) + "}"


def _krl_frame(t: FloatArray) -> str:
    abc = matrix_to_abc_deg(t[:3, :3])
    return _krl_aggregate(dict(zip(("X", "Y", "Z", "A", "B", "C"), [*t[:3, 3], *abc], strict=True)))


def _krl_values(text: str) -> dict[str, float]:
    inner = text.strip()
    if not (inner.startswith("{") and inner.endswith("}")):
        return {"": float(inner)}
    out = {}
    for part in inner[1:-1].split(","):
        key, _, value = part.strip().partition(" ")
        out[key.upper()] = float(value)
    return out


def format_kuka(listing: ControllerParams) -> str:
    """The KRL data-list listing (module docstring)."""
    lines = [
        "&ACCESS RV",
        "&COMMENT comp-daemon identified kinematic parameters",
        "DEFDAT CD_KINEMATICS PUBLIC",
        "; comp-daemon identified kinematic parameters, listed in KUKA's style for review:",
        "; not a machine-data file that a controller loads as it is.",
        *(f"; {line}" for line in listing.info.lines()),
        "; units: lengths mm, angles deg; FRAME = {X, Y, Z mm; A, B, C deg: Rz(A)*Ry(B)*Rx(C)}",
        "; MDH: T(j-1,j) = Rz(THETA + SIGN*Aj)*Tz(D)*Tx(A)*Rx(ALPHA)*Ry(BETA); THETA is the zero offset",
        "; CD_NOM_AXj: the robot description's values; CD_AXj: the identified values",
        "STRUC CD_MDH REAL A,ALPHA,D,THETA,BETA",
    ]
    for j in range(6):
        nom = {_KRL_FIELDS[n]: listing.nominal[j, k] for k, (n, _) in enumerate(JOINT_FIELDS)}
        ident = {_KRL_FIELDS[n]: listing.identified[j, k] for k, (n, _) in enumerate(JOINT_FIELDS)}
        delta = listing.identified[j] - listing.nominal[j]
        deltas = ", ".join(
            f"{n} {delta[k]:+.6g} {u}{sigma_note(listing, f'{n}{j + 1}')}"
            for k, (n, u) in enumerate(JOINT_FIELDS)
        )
        lines += [
            f"; axis {j + 1}: delta {deltas}",
            f"DECL INT CD_SIGN{j + 1}={int(listing.sign[j])}",
            f"DECL CD_MDH CD_NOM_AX{j + 1}={_krl_aggregate(nom)}",
            f"DECL CD_MDH CD_AX{j + 1}={_krl_aggregate(ident)}",
        ]
    tool_kuka = [FLANGE_R_KUKA_TOOL.T @ t for t in (listing.tool_nominal_mm, listing.tool_mm)]
    lines += [
        "; the chain's root (the frame axis 1 turns in) in the robot base frame; nominal: all zero",
        f"DECL FRAME CD_BASE={_krl_frame(listing.base_T_root)}",
        "; the robot base frame in the measurement frame (tracker), for information",
        f"DECL FRAME CD_REGISTRATION={_krl_frame(listing.meas_T_base)}",
        "; the TCP in KUKA's flange frame (x out of the flange), as $TOOL; A, B, C not identified",
        f"DECL FRAME CD_NOM_TOOL={_krl_frame(frame(tool_kuka[0], np.eye(3)))}",
        f"DECL FRAME CD_TOOL={_krl_frame(frame(tool_kuka[1], np.eye(3)))}",
    ]
    if listing.effects is not None:
        lines += [
            "; non-geometric effects of the joints (comp-daemon's effect catalogue)",
            f"DECL INT CD_HARMONICS={listing.n_harmonics}",
            f"DECL REAL CD_T_REF_C={num(listing.t_ref_c)}",
        ]
        for name, value in listing.effects.items():
            unit = effect_unit(name, listing.n_harmonics)
            meaning = effect_meaning(name, listing.n_harmonics)
            note = sigma_note(listing, name)
            lines.append(f"DECL REAL CD_EFF_{name}={num(value)} ; {meaning}, {unit}{note}")
    lines.append("ENDDAT")
    return "\n".join(lines) + "\n"


def parse_kuka(text: str, where: str = "<krl>") -> ControllerParams:
    header: list[str] = []
    decl: dict[str, str] = {}
    for line in text.splitlines():
        code, _, comment = line.partition(";")
        if not code.strip():
            header.append(comment)
            continue
        m = _KRL_DECL.match(code)
        if m:
            decl[m.group(2)] = m.group(3)
    info = ListingInfo.of_lines(dict(header_pairs(header)))

    def values(name: str) -> dict[str, float]:
        if name not in decl:
            raise ValueError(f"{where}: no DECL of {name}")
        try:
            return _krl_values(decl[name])
        except ValueError as exc:
            raise ValueError(f"{where}: {name}: {exc}") from None

    def krl_frame(name: str) -> FloatArray:
        v = values(name)
        return frame(
            np.array([v["X"], v["Y"], v["Z"]]), abc_deg_to_matrix(np.array([v["A"], v["B"], v["C"]]))
        )

    rows: dict[str, tuple[float, float]] = {}
    for j in range(1, 7):
        nom, ident = values(f"CD_NOM_AX{j}"), values(f"CD_AX{j}")
        for n, _ in JOINT_FIELDS:
            rows[f"{n}{j}"] = (nom[_KRL_FIELDS[n]], ident[_KRL_FIELDS[n]])
        sign = values(f"CD_SIGN{j}")[""]
        rows[f"sign{j}"] = (sign, sign)
    tools = [FLANGE_R_KUKA_TOOL @ krl_frame(n)[:3, 3] for n in ("CD_NOM_TOOL", "CD_TOOL")]
    for i, a in enumerate("xyz"):
        rows[f"tool_{a}"] = (tools[0][i], tools[1][i])
    for stem, name in (("base", "CD_BASE"), ("registration", "CD_REGISTRATION")):
        t = krl_frame(name)
        v = [*t[:3, 3], *matrix_to_rotvec_deg(t[:3, :3])]
        rows.update({f"{stem}_{a}": (v[i], v[i]) for i, a in enumerate(FRAME_AXES)})
    if "CD_HARMONICS" in decl:
        rows["n_harmonics"] = (0.0, values("CD_HARMONICS")[""])
        rows["t_ref_c"] = (0.0, values("CD_T_REF_C")[""])
        for key in decl:
            if key.startswith("CD_EFF_"):
                rows[key.removeprefix("CD_EFF_")] = (0.0, values(key)[""])
    return with_frames(of_rows(info, rows, where), krl_frame("CD_BASE"), krl_frame("CD_REGISTRATION"))


# --------------------------------------------------------------------------------------- targets
_AXES = ("A1", "A2", "A3", "A4", "A5", "A6")
_EXTERNAL = ",".join(f"E{k} 0.0" for k in range(1, 7))


def format_krl_targets(targets: TargetList, module: str, header: Sequence[str] = ()) -> str:
    """The ``.dat`` of ``targets`` (module docstring), ``DEFDAT <module>``; ``header``: comment lines."""
    lines = [
        "&ACCESS RVP",
        "&REL 1",
        f"DEFDAT {module} PUBLIC",
        *(f"; {line}" for line in header),
        "; XA_<name>: compensated axis values A1..A6 (deg): move there with PTP XA_<name>",
        "; XP_<name>: the nominal Cartesian target (X, Y, Z mm; A, B, C deg of the tool frame), for",
        ";            reference: a motion to it runs on the controller's nominal model, uncompensated",
    ]
    abc = targets.tool_abc_deg
    for i, name in enumerate(targets.names):
        axes = ",".join(f"{k} {num(v)}" for k, v in zip(_AXES, targets.a_deg[i], strict=True))
        pose = ",".join(f"{k} {num(v)}" for k, v in zip("XYZABC", [*targets.xyz_mm[i], *abc[i]], strict=True))
        lines += [
            f"DECL E6AXIS XA_{name}={{{axes},{_EXTERNAL}}}",
            f"DECL E6POS XP_{name}={{{pose},{_EXTERNAL}}}",
        ]
    lines.append("ENDDAT")
    return "\n".join(lines) + "\n"


def parse_krl_targets(text: str, where: str = "<dat>") -> TargetList:
    axes: dict[str, dict[str, float]] = {}
    poses: dict[str, dict[str, float]] = {}
    for line in text.splitlines():
        m = _KRL_DECL.match(line.partition(";")[0])
        if m is None:
            continue
        kind, name = m.group(1).upper(), m.group(2)
        if kind == "E6AXIS" and name.startswith("XA_"):
            axes[name[3:]] = _krl_values(m.group(3))
        elif kind == "E6POS" and name.startswith("XP_"):
            poses[name[3:]] = _krl_values(m.group(3))
    names = paired_names(list(axes), poses, where, "E6AXIS XA_<name>", "E6POS XP_")
    abc = np.array([[poses[n][k] for k in "ABC"] for n in names])
    return TargetList(
        names=names,
        a_deg=np.array([[axes[n][k] for k in _AXES] for n in names]),
        xyz_mm=np.array([[poses[n][k] for k in "XYZ"] for n in names]),
        flange_R=flange_rotation_of_tool_abc(abc),
    )
