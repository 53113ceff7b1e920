"""ABB listings: the identified parameters as a ``MOC.cfg``-like text, compensated targets in RAPID.

Parameters (:func:`format_abb` / :func:`parse_abb`): ``CFG_1.0`` sections of comp-daemon's own
types (``CD_MODEL``, ``CD_ARM``, ``CD_FRAME``, ``CD_EFFECT``; not ABB's ``ARM`` or ``ROBOT``
types), one instance a line: ``CD_ARM`` per axis (``-name "rob1_<j>"``, ``-sign``, ``-a_mm``,
``-alpha_deg``, ``-d_mm``, ``-theta_offset_deg``, ``-beta_deg`` and the same with ``nominal_``);
``CD_FRAME`` ``base`` (the chain's root in the robot base frame), ``registration`` (the robot base
frame in the measurement frame), ``nominal_tool`` / ``tool`` (the TCP in the flange frame, z out of
the flange as ABB's ``tool0``), each ``-x_mm -y_mm -z_mm`` and the quaternion ``-q1..-q4`` (w, x,
y, z). For review: no controller loads it as it is.

Targets (:func:`format_rapid_targets` / :func:`parse_rapid_targets`): ``MODULE <module>``, per
target ``CONST jointtarget j<name>`` (the compensated axis values, deg, for ``MoveAbsJ``) and
``CONST robtarget p<name>`` (the nominal Cartesian target: ``[x, y, z]`` mm of the TCP, the
flange's orientation ``[q1, q2, q3, q4]``, ``confdata`` ``[cf1, cf4, cf6, cfx]`` with cf1, cf4, cf6
the quadrants of the compensated axes 1, 4, 6 and cfx not derived (0): for reference, move by the
jointtarget). External axes 9E+09 (none).
"""

from __future__ import annotations

import json
import re
import shlex
from collections.abc import Sequence

import numpy as np

from comp_daemon.export.frames import (
    FloatArray,
    frame,
    matrix_to_quaternion,
    matrix_to_rotvec_deg,
    num,
    quaternion_to_matrix,
)
from comp_daemon.export.params import (
    FRAME_AXES,
    JOINT_FIELDS,
    ControllerParams,
    ListingInfo,
    effect_unit,
    of_rows,
    with_frames,
)
from comp_daemon.export.targets import TargetList, paired_names

__all__ = ["format_abb", "format_rapid_targets", "parse_abb", "parse_rapid_targets"]


# ------------------------------------------------------------------------------------------- abb
_ABB_FIELDS = {
    "a": "a_mm",
    "alpha": "alpha_deg",
    "d": "d_mm",
    "theta": "theta_offset_deg",
    "beta": "beta_deg",
}


def _abb_frame(name: str, t: FloatArray) -> str:
    q = matrix_to_quaternion(t[:3, :3])
    parts = [f'-name "{name}"']
    parts += [f"-{k}_mm {num(v)}" for k, v in zip("xyz", t[:3, 3], strict=True)]
    parts += [f"-q{i + 1} {num(v)}" for i, v in enumerate(q)]
    return "      " + " ".join(parts)


def format_abb(listing: ControllerParams) -> str:
    """The ``MOC.cfg``-like listing (module docstring)."""
    info = listing.info
    meta = [
        f'-robot "{info.robot}"',
        f'-model "{info.model}"',
        f'-model_id "{info.model_id}"',
        f'-fit_date "{info.fit_date}"',
    ]
    meta += [
        f"-{k} {num(v)}"
        for k, v in (("fit_rms_mm", info.fit_rms_mm), ("check_rms_mm", info.check_rms_mm))
        if v is not None
    ]
    if listing.effects is not None:
        meta += [f"-n_harmonics {listing.n_harmonics}", f"-t_ref_c {num(listing.t_ref_c)}"]
    lines = [
        "MOC:CFG_1.0:6:0::",
        "#",
        "# comp-daemon identified kinematic parameters, listed in the style of an ABB MOC.cfg for review:",
        "# not a configuration that a controller loads as it is.",
        *(f"# {line}" for line in info.lines()),
        "# units: lengths mm, angles deg; quaternions q1..q4 = w, x, y, z",
        "# MDH: T(j-1,j) = Rz(theta_offset + sign*Aj)*Tz(d)*Tx(a)*Rx(alpha)*Ry(beta)",
        "#",
        "CD_MODEL:",
        "",
        "      " + " ".join(meta),
        "#",
        "CD_ARM:",
        "",
    ]
    for j in range(6):
        parts = [f'-name "rob1_{j + 1}"', f"-sign {int(listing.sign[j])}"]
        parts += [
            f"-{_ABB_FIELDS[n]} {num(listing.identified[j, k])}" for k, (n, _) in enumerate(JOINT_FIELDS)
        ]
        parts += [
            f"-nominal_{_ABB_FIELDS[n]} {num(listing.nominal[j, k])}" for k, (n, _) in enumerate(JOINT_FIELDS)
        ]
        lines.append("      " + " ".join(parts))
    lines += [
        "#",
        "# base: the chain's root in the robot base frame (nominal: identity); registration: the",
        "# robot base frame in the measurement frame; tool: the TCP in the flange frame (z out of",
        "# the flange, as tool0)",
        "CD_FRAME:",
        "",
        _abb_frame("base", listing.base_T_root),
        _abb_frame("registration", listing.meas_T_base),
        _abb_frame("nominal_tool", frame(listing.tool_nominal_mm, np.eye(3))),
        _abb_frame("tool", frame(listing.tool_mm, np.eye(3))),
    ]
    if listing.effects is not None:
        lines += [
            "#",
            "# non-geometric effects of the joints (comp-daemon's effect catalogue)",
            "CD_EFFECT:",
            "",
        ]
        for name, value in listing.effects.items():
            unit = effect_unit(name, listing.n_harmonics)
            lines.append(f'      -name "{name}" -value {num(value)} -unit "{unit}"')
    return "\n".join(lines) + "\n"


def parse_abb(text: str, where: str = "<cfg>") -> ControllerParams:
    sections: dict[str, list[dict[str, str]]] = {}
    current: list[dict[str, str]] | None = None
    for line in text.splitlines():
        if not line.strip() or line.startswith("#") or line.startswith("MOC:"):
            continue
        if not line[0].isspace() and line.rstrip().endswith(":"):
            current = sections.setdefault(line.strip()[:-1], [])
            continue
        if current is None:
            raise ValueError(f"{where}: an instance outside a section: {line.strip()[:40]}")
        words = shlex.split(line)
        current.append({words[i].lstrip("-"): words[i + 1] for i in range(0, len(words) - 1, 2)})

    def section(name: str) -> list[dict[str, str]]:
        if name not in sections:
            raise ValueError(f"{where}: no {name} section")
        return sections[name]

    meta = section("CD_MODEL")[0]
    info = ListingInfo(
        robot=meta.get("robot", ""),
        model=meta.get("model", ""),
        model_id=meta.get("model_id", ""),
        fit_date=meta.get("fit_date", ""),
        fit_rms_mm=float(meta["fit_rms_mm"]) if "fit_rms_mm" in meta else None,
        check_rms_mm=float(meta["check_rms_mm"]) if "check_rms_mm" in meta else None,
    )
    rows: dict[str, tuple[float, float]] = {}
    arms = {a["name"]: a for a in section("CD_ARM")}
    for j in range(1, 7):
        arm = arms.get(f"rob1_{j}")
        if arm is None:
            raise ValueError(f"{where}: no CD_ARM instance rob1_{j}")
        for n, _ in JOINT_FIELDS:
            rows[f"{n}{j}"] = (float(arm[f"nominal_{_ABB_FIELDS[n]}"]), float(arm[_ABB_FIELDS[n]]))
        rows[f"sign{j}"] = (float(arm["sign"]), float(arm["sign"]))
    frames = {}
    for inst in section("CD_FRAME"):
        p = np.array([float(inst[f"{k}_mm"]) for k in "xyz"])
        q = np.array([float(inst[f"q{i}"]) for i in range(1, 5)])
        frames[inst["name"]] = frame(p, quaternion_to_matrix(q))
    missing = {"base", "registration", "nominal_tool", "tool"} - set(frames)
    if missing:
        raise ValueError(f"{where}: CD_FRAME lacks {', '.join(sorted(missing))}")
    for i, a in enumerate("xyz"):
        rows[f"tool_{a}"] = (frames["nominal_tool"][i, 3], frames["tool"][i, 3])
    for stem in ("base", "registration"):
        t = frames[stem]
        v = [*t[:3, 3], *matrix_to_rotvec_deg(t[:3, :3])]
        rows.update({f"{stem}_{a}": (v[i], v[i]) for i, a in enumerate(FRAME_AXES)})
    if "n_harmonics" in meta:
        rows["n_harmonics"] = (0.0, float(meta["n_harmonics"]))
        rows["t_ref_c"] = (0.0, float(meta["t_ref_c"]))
        for inst in sections.get("CD_EFFECT", []):
            rows[inst["name"]] = (0.0, float(inst["value"]))
    return with_frames(of_rows(info, rows, where), frames["base"], frames["registration"])


# --------------------------------------------------------------------------------------- targets
_NO_EXTERNAL = "[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]"
_CONST = re.compile(r"^\s*CONST\s+(jointtarget|robtarget)\s+(\w+)\s*:=\s*(\[.*\])\s*;", re.IGNORECASE)


def _quadrants(a_deg: FloatArray) -> FloatArray:
    """ABB's quadrant numbers of axis angles: 0 for [0°, 90°), 1 for [90°, 180°), −1 for [−90°, 0°) …"""
    return np.floor(np.asarray(a_deg) / 90.0)


def format_rapid_targets(targets: TargetList, module: str, header: Sequence[str] = ()) -> str:
    """The RAPID module of ``targets`` (module docstring), ``MODULE <module>``; ``header``: comments."""
    lines = [
        f"MODULE {module}",
        *(f"    ! {line}" for line in header),
        "    ! j<name>: compensated axis values (deg): MoveAbsJ j<name>, ...",
        "    ! p<name>: the nominal Cartesian target (mm; flange orientation q1..q4), for reference:",
        "    !          a motion to it runs on the controller's nominal model, uncompensated;",
        "    !          confdata cfx is not derived (0)",
    ]
    quat = matrix_to_quaternion(targets.flange_R)
    cf = _quadrants(targets.a_deg[:, [0, 3, 5]])
    for i, name in enumerate(targets.names):
        axes = ",".join(num(v) for v in targets.a_deg[i])
        pos = ",".join(num(v) for v in targets.xyz_mm[i])
        q = ",".join(num(v) for v in quat[i])
        conf = ",".join(str(int(c)) for c in cf[i])
        lines += [
            f"    CONST jointtarget j{name} := [[{axes}],{_NO_EXTERNAL}];",
            f"    CONST robtarget p{name} := [[{pos}],[{q}],[{conf},0],{_NO_EXTERNAL}];",
        ]
    lines.append("ENDMODULE")
    return "\n".join(lines) + "\n"


def parse_rapid_targets(text: str, where: str = "<mod>") -> TargetList:
    joints: dict[str, list[float]] = {}
    robs: dict[str, list[list[float]]] = {}
    for line in text.splitlines():
        m = _CONST.match(line.partition("!")[0])
        if m is None:
            continue
        try:
            value = json.loads(m.group(3))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{where}: {m.group(2)}: {exc.msg}") from None
        if m.group(1).lower() == "jointtarget" and m.group(2).startswith("j"):
            joints[m.group(2)[1:]] = value[0]
        elif m.group(1).lower() == "robtarget" and m.group(2).startswith("p"):
            robs[m.group(2)[1:]] = value
    names = paired_names(list(joints), robs, where, "CONST jointtarget j<name>", "CONST robtarget p")
    return TargetList(
        names=names,
        a_deg=np.array([joints[n] for n in names], dtype=float),
        xyz_mm=np.array([robs[n][0] for n in names], dtype=float),
        flange_R=quaternion_to_matrix(np.array([robs[n][1] for n in names], dtype=float)),
    )
