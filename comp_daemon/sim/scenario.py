"""Scenarios of the simulated cell: the hidden robot, its effects, noise, motion and the measurement box.

A scenario is a TOML file (presets in ``comp_daemon/sim/scenarios/``, or any path). It fixes one
*hidden* robot: its geometric errors are drawn once from ``[scenario].seed`` (or given explicitly),
so the same scenario is always the same robot; a campaign's own seed only changes which poses are
sampled and the noise. Units are in the field names (mm, deg, kg, °C, s, N m). Tables::

    [scenario]   name, robot (preset or path), seed, description
    [geometric]  standard deviations of the hidden DH / base / tool errors (normal draws):
                 theta_deg, d_mm, a_mm, alpha_deg, beta_deg (only on ``beta_joints``), base_mm,
                 base_deg, tool_mm;  [geometric.values] sets any PARAM_NAMES entry exactly
                 (rad / mm, as in comp_daemon.kinematics.params)
    [effects]    backlash_deg (6), ratio (6), cyclic_sin_deg / cyclic_cos_deg (6 × K),
                 compliance_rad_per_nm (6), thermal_per_k, t_ref_c   (docs/diagnosis-output.md definitions);
                 drift_mm_per_h (3), drift_mm_per_h2 (3): the TCP drifts by v·t + w·t² (t: plant
                 time in h, robot base frame), step_deg (6), step_at_s: each joint's zero changes
                 by step_deg from plant time step_at_s on (the catalogue's drift and step; no data
                 column names them)
    [noise]      joint_repeatability_deg (6, σ of a fresh joint offset per motion),
                 tracker_sigma_mm (σ per axis)
    [motion]     v_max_deg_s (6), a_max_deg_s2 (6), servo_time_constant_s, settle_tol_deg, dwell_s
    [cell]       temp_start_c, temp_drift_k_per_h, temp_amplitude_k, temp_period_h,
                 tracker_xyz_mm / tracker_abc_deg (pose of the robot base in the tracker frame;
                 zeros: the tracker reports in the robot base frame), grating_joints, grating_radius_mm
    [campaign]   box_min_mm, box_max_mm (robot base frame), abc_min_deg, abc_max_deg (KUKA A, B, C
                 of the tool frame), home_deg, payload_kg (list: each pose gets one), check_fraction,
                 repeats, seed, targets (reflectors on the flange per pose, default 1; see
                 :func:`comp_daemon.sim.campaign.reflector_offsets_mm`)

The tool frame of A, B, C is KUKA's: x along the tool (the flange frame's z), so A = B = C = 0 is
the tool pointing along +x of the base, as at the KR210's home pose.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import (
    JOINT_PARAM_KINDS,
    N_PARAMS,
    PARAM_NAMES,
    KinematicParams,
    joint_param_index,
)
from comp_daemon.models.effects import EffectParams
from comp_daemon.robot.description import RobotDescription, load_robot
from comp_daemon.sim_client import preset_scenarios

__all__ = [
    "PRESET_SCENARIOS",
    "CampaignSettings",
    "CellSettings",
    "GeometricErrors",
    "MotionSettings",
    "NoiseSettings",
    "Scenario",
    "ScenarioError",
    "load_scenario",
    "parse_scenario_toml",
]

#: The packaged presets (``comp_daemon/sim/scenarios/NAME.toml``).
PRESET_SCENARIOS: tuple[str, ...] = preset_scenarios()


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the table and field."""


@dataclass(frozen=True, slots=True)
class GeometricErrors:
    """How the hidden geometric errors are drawn (σ of normal draws) and explicit overrides."""

    theta_deg: float = 0.0
    d_mm: float = 0.0
    a_mm: float = 0.0
    alpha_deg: float = 0.0
    beta_deg: float = 0.0
    beta_joints: tuple[int, ...] = ()
    base_mm: float = 0.0
    base_deg: float = 0.0
    tool_mm: float = 0.0
    values: dict[str, float] = field(default_factory=dict)

    def draw(self, seed: int) -> NDArray[np.float64]:
        """The 39-entry error vector (PARAM_NAMES layout, rad / mm) of this hidden robot."""
        rng = np.random.default_rng(seed)
        z = rng.standard_normal(N_PARAMS)
        sigma = np.zeros(N_PARAMS)
        per_kind = {
            "theta": math.radians(self.theta_deg),
            "d": self.d_mm,
            "a": self.a_mm,
            "alpha": math.radians(self.alpha_deg),
            "beta": 0.0,
        }
        for joint in range(1, 7):
            for kind in JOINT_PARAM_KINDS:
                sigma[joint_param_index(kind, joint)] = per_kind[kind]
        for joint in self.beta_joints:
            sigma[joint_param_index("beta", joint)] = math.radians(self.beta_deg)
        sigma[30:33] = self.base_mm
        sigma[33:36] = math.radians(self.base_deg)
        sigma[36:39] = self.tool_mm
        dx = sigma * z
        for name, value in self.values.items():
            dx[PARAM_NAMES.index(name)] = value
        return dx


@dataclass(frozen=True, slots=True)
class NoiseSettings:
    joint_repeatability_deg: NDArray[np.float64]
    tracker_sigma_mm: float = 0.01


@dataclass(frozen=True, slots=True)
class MotionSettings:
    v_max_deg_s: NDArray[np.float64]
    a_max_deg_s2: NDArray[np.float64]
    servo_time_constant_s: float = 0.015
    settle_tol_deg: float = 1e-6
    dwell_s: float = 0.5


@dataclass(frozen=True, slots=True)
class CellSettings:
    temp_start_c: float = 20.0
    temp_drift_k_per_h: float = 0.0
    temp_amplitude_k: float = 0.0
    temp_period_h: float = 24.0
    tracker_xyz_mm: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    tracker_abc_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    grating_joints: tuple[int, ...] = (1, 2, 3)
    grating_radius_mm: float = 400.0

    def temperature_c(self, t_s: float | NDArray[np.float64]) -> Any:
        """Structure temperature at campaign time ``t_s``: start + linear drift + a daily-like wave."""
        t_h = np.asarray(t_s, dtype=float) / 3600.0
        wave = self.temp_amplitude_k * np.sin(2.0 * np.pi * t_h / self.temp_period_h)
        return self.temp_start_c + self.temp_drift_k_per_h * t_h + wave


@dataclass(frozen=True, slots=True)
class CampaignSettings:
    box_min_mm: NDArray[np.float64]
    box_max_mm: NDArray[np.float64]
    abc_min_deg: NDArray[np.float64]
    abc_max_deg: NDArray[np.float64]
    home_deg: NDArray[np.float64]
    payload_kg: tuple[float, ...] = (0.0,)
    check_fraction: float = 0.4
    repeats: int = 1
    seed: int = 0
    targets: int = 1  # reflectors on the flange measured at every pose (x,y,z, then x2,y2,z2 …)


@dataclass(frozen=True, slots=True)
class Scenario:
    """A hidden robot and its cell. :meth:`true_params` and :attr:`effects` are the ground truth."""

    name: str
    description: str
    robot: RobotDescription
    seed: int
    geometric: GeometricErrors
    effects: EffectParams
    noise: NoiseSettings
    motion: MotionSettings
    cell: CellSettings
    campaign: CampaignSettings
    source: str = "<string>"

    def true_dx(self) -> NDArray[np.float64]:
        """The hidden geometric error vector (PARAM_NAMES layout)."""
        return self.geometric.draw(self.seed)

    def true_params(self) -> KinematicParams:
        """The hidden robot's kinematic parameters, in its own base frame (nominal + errors)."""
        params = KinematicParams.from_robot(self.robot)
        return params.apply(self.true_dx())

    def tracker_T_base(self) -> NDArray[np.float64]:
        """(4, 4) pose of the robot base frame in the tracker's frame."""
        from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix

        out = np.eye(4)
        out[:3, :3] = abc_deg_to_matrix(self.cell.tracker_abc_deg)
        out[:3, 3] = self.cell.tracker_xyz_mm
        return out


# ---------------------------------------------------------------------------------------------
# parsing
# ---------------------------------------------------------------------------------------------
def _table(doc: dict[str, Any], name: str, where: str, allowed: set[str]) -> dict[str, Any]:
    value = doc.get(name, {})
    if not isinstance(value, dict):
        raise ScenarioError(f"{where}: [{name}] must be a table")
    for key in value:
        if key not in allowed:
            raise ScenarioError(
                f"{where} [{name}]: unknown field '{key}' (allowed: {', '.join(sorted(allowed))})"
            )
    return value


def _num(
    table: dict[str, Any], key: str, where: str, default: float | None = None, *, lo: float | None = None
) -> float:
    if key not in table:
        if default is None:
            raise ScenarioError(f"{where}: missing field '{key}'")
        return default
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ScenarioError(f"{where}.{key}: expected a finite number, got {value!r}")
    if lo is not None and value < lo:
        raise ScenarioError(f"{where}.{key}: must be >= {lo}, got {value}")
    return float(value)


def _arr(
    table: dict[str, Any],
    key: str,
    where: str,
    shape: tuple[int, ...],
    default: Any = None,
    *,
    lo: float | None = None,
) -> NDArray[np.float64]:
    if key not in table:
        if default is None:
            raise ScenarioError(f"{where}: missing field '{key}'")
        return np.array(default, dtype=float)
    try:
        out = np.array(table[key], dtype=float)
    except (TypeError, ValueError):
        raise ScenarioError(f"{where}.{key}: expected numbers, got {table[key]!r}") from None
    if out.shape != shape:
        raise ScenarioError(f"{where}.{key}: expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ScenarioError(f"{where}.{key}: values must be finite")
    if lo is not None and np.any(out < lo):
        raise ScenarioError(f"{where}.{key}: values must be >= {lo}")
    return out


def _joints(table: dict[str, Any], key: str, where: str, default: tuple[int, ...]) -> tuple[int, ...]:
    value = table.get(key, list(default))
    if not isinstance(value, list) or not all(isinstance(j, int) and 1 <= j <= 6 for j in value):
        raise ScenarioError(f"{where}.{key}: expected a list of joint numbers 1..6, got {value!r}")
    return tuple(value)


def _count(table: dict[str, Any], key: str, where: str, default: int, *, least: int) -> int:
    """An integer field (not a bool) of at least ``least``."""
    value = table.get(key, default)
    if not isinstance(value, int) or isinstance(value, bool) or value < least:
        raise ScenarioError(f"{where}.{key}: expected an integer >= {least}, got {value!r}")
    return value


# one parser per table: each takes the document and the source, and names the table in its refusals


def _parse_header(doc: dict[str, Any], source: str) -> tuple[str, str, RobotDescription, int]:
    """[scenario]: name, description, the robot (a file beside the scenario file first) and the seed."""
    w = f"{source} [scenario]"
    sc = _table(doc, "scenario", source, {"name", "robot", "seed", "description"})
    name = sc.get("name")
    if not isinstance(name, str) or not name:
        raise ScenarioError(f"{w}: missing field 'name' (a non-empty string)")
    robot_ref = sc.get("robot")
    if not isinstance(robot_ref, str):
        raise ScenarioError(f"{w}: missing field 'robot' (a preset name or a path)")
    if not source.startswith(("preset:", "<")):
        candidate = Path(source).parent / robot_ref  # a robot file beside the scenario file
        robot_ref = str(candidate) if candidate.is_file() else robot_ref
    robot = load_robot(robot_ref)
    seed = _count(sc, "seed", w, 0, least=0)
    return name, str(sc.get("description", "")), robot, seed


def _parse_geometric(doc: dict[str, Any], source: str) -> GeometricErrors:
    """[geometric]: the σ of each kind of hidden error (>= 0) and exact values by PARAM_NAMES entry."""
    w = f"{source} [geometric]"
    kinds = {"theta_deg", "d_mm", "a_mm", "alpha_deg", "beta_deg", "base_mm", "base_deg", "tool_mm"}
    geo_t = _table(doc, "geometric", source, kinds | {"beta_joints", "values"})
    values_raw = geo_t.get("values", {})
    if not isinstance(values_raw, dict):
        raise ScenarioError(f"{w}.values: must be a table of PARAM_NAMES entries")
    values: dict[str, float] = {}
    for key in values_raw:
        if key not in PARAM_NAMES:
            raise ScenarioError(
                f"{w}.values: unknown parameter '{key}' (expected one of PARAM_NAMES, e.g. theta2)"
            )
        values[key] = _num(values_raw, key, f"{w}.values")
    return GeometricErrors(
        **{k: _num(geo_t, k, w, 0.0, lo=0.0) for k in kinds},
        beta_joints=_joints(geo_t, "beta_joints", w, ()),
        values=values,
    )


_EFFECT_FIELDS = {
    "backlash_deg",
    "ratio",
    "cyclic_sin_deg",
    "cyclic_cos_deg",
    "compliance_rad_per_nm",
    "thermal_per_k",
    "t_ref_c",
    "drift_mm_per_h",
    "drift_mm_per_h2",
    "step_deg",
    "step_at_s",
}


def _parse_effects(doc: dict[str, Any], source: str) -> EffectParams:
    """[effects]: the hidden robot's joint and time effects; the drift as the catalogue's named
    arrays, a step only with its moment, as many harmonics as ``cyclic_sin_deg``'s first row has."""
    w = f"{source} [effects]"
    eff_t = _table(doc, "effects", source, _EFFECT_FIELDS)
    drift_v = _arr(eff_t, "drift_mm_per_h", w, (3,), [0.0] * 3)
    drift_w = _arr(eff_t, "drift_mm_per_h2", w, (3,), [0.0] * 3)
    drift = {
        f"drift_{axis}_mm_per_h{power}": float(values[i])
        for power, values in ((1, drift_v), (2, drift_w))
        for i, axis in enumerate("xyz")
    }
    step_deg = _arr(eff_t, "step_deg", w, (6,), [0.0] * 6)
    if np.any(step_deg != 0.0) and "step_at_s" not in eff_t:
        raise ScenarioError(f"{w}: step_deg needs step_at_s (the plant time of the change, s)")
    step_at_s = _num(eff_t, "step_at_s", w, math.inf, lo=0.0)
    sin_raw = eff_t.get("cyclic_sin_deg", [[]] * 6)
    n_harm = len(sin_raw[0]) if isinstance(sin_raw, list) and sin_raw and isinstance(sin_raw[0], list) else 0
    zeros_k = np.zeros((6, n_harm)).tolist()
    return EffectParams(
        backlash_deg=_arr(eff_t, "backlash_deg", w, (6,), [0.0] * 6, lo=0.0),
        ratio=_arr(eff_t, "ratio", w, (6,), [0.0] * 6),
        cyclic_sin_deg=_arr(eff_t, "cyclic_sin_deg", w, (6, n_harm), zeros_k),
        cyclic_cos_deg=_arr(eff_t, "cyclic_cos_deg", w, (6, n_harm), zeros_k),
        compliance_rad_per_nm=_arr(eff_t, "compliance_rad_per_nm", w, (6,), [0.0] * 6, lo=0.0),
        thermal_per_k=_num(eff_t, "thermal_per_k", w, 0.0),
        t_ref_c=_num(eff_t, "t_ref_c", w, 20.0),
        step_deg=step_deg,
        step_at=step_at_s / 3600.0,
        arrays=drift,
    )


def _parse_noise(doc: dict[str, Any], source: str) -> NoiseSettings:
    """[noise]: joint repeatability and tracker σ, both >= 0."""
    w = f"{source} [noise]"
    noise_t = _table(doc, "noise", source, {"joint_repeatability_deg", "tracker_sigma_mm"})
    return NoiseSettings(
        joint_repeatability_deg=_arr(noise_t, "joint_repeatability_deg", w, (6,), [0.0] * 6, lo=0.0),
        tracker_sigma_mm=_num(noise_t, "tracker_sigma_mm", w, 0.01, lo=0.0),
    )


def _parse_motion(doc: dict[str, Any], source: str) -> MotionSettings:
    """[motion]: axis speed and acceleration limits, servo lag, settling tolerance and dwell."""
    w = f"{source} [motion]"
    mot_t = _table(
        doc,
        "motion",
        source,
        {"v_max_deg_s", "a_max_deg_s2", "servo_time_constant_s", "settle_tol_deg", "dwell_s"},
    )
    return MotionSettings(
        v_max_deg_s=_arr(mot_t, "v_max_deg_s", w, (6,), [100.0, 90.0, 90.0, 150.0, 150.0, 200.0], lo=1e-6),
        a_max_deg_s2=_arr(
            mot_t, "a_max_deg_s2", w, (6,), [200.0, 180.0, 180.0, 300.0, 300.0, 400.0], lo=1e-6
        ),
        servo_time_constant_s=_num(mot_t, "servo_time_constant_s", w, 0.015, lo=1e-6),
        settle_tol_deg=_num(mot_t, "settle_tol_deg", w, 1e-6, lo=1e-12),
        dwell_s=_num(mot_t, "dwell_s", w, 0.5, lo=0.0),
    )


_CELL_FIELDS = {
    "temp_start_c",
    "temp_drift_k_per_h",
    "temp_amplitude_k",
    "temp_period_h",
    "tracker_xyz_mm",
    "tracker_abc_deg",
    "grating_joints",
    "grating_radius_mm",
}


def _parse_cell(doc: dict[str, Any], source: str) -> CellSettings:
    """[cell]: the temperature's course, the tracker's pose and the gratings."""
    w = f"{source} [cell]"
    cell_t = _table(doc, "cell", source, _CELL_FIELDS)
    return CellSettings(
        temp_start_c=_num(cell_t, "temp_start_c", w, 20.0),
        temp_drift_k_per_h=_num(cell_t, "temp_drift_k_per_h", w, 0.0),
        temp_amplitude_k=_num(cell_t, "temp_amplitude_k", w, 0.0),
        temp_period_h=_num(cell_t, "temp_period_h", w, 24.0, lo=1e-6),
        tracker_xyz_mm=_arr(cell_t, "tracker_xyz_mm", w, (3,), [0.0] * 3),
        tracker_abc_deg=_arr(cell_t, "tracker_abc_deg", w, (3,), [0.0] * 3),
        grating_joints=_joints(cell_t, "grating_joints", w, (1, 2, 3)),
        grating_radius_mm=_num(cell_t, "grating_radius_mm", w, 400.0, lo=1e-3),
    )


_CAMPAIGN_FIELDS = {
    "box_min_mm",
    "box_max_mm",
    "abc_min_deg",
    "abc_max_deg",
    "home_deg",
    "payload_kg",
    "check_fraction",
    "repeats",
    "seed",
    "targets",
}


def _parse_campaign(doc: dict[str, Any], source: str, robot: RobotDescription) -> CampaignSettings:
    """[campaign]: a non-empty box and A, B, C range, a home pose within ``robot``'s axis limits, at
    least one payload, a check fraction below 1, and the counts."""
    w = f"{source} [campaign]"
    cam_t = _table(doc, "campaign", source, _CAMPAIGN_FIELDS)
    box_min = _arr(cam_t, "box_min_mm", w, (3,))
    box_max = _arr(cam_t, "box_max_mm", w, (3,))
    if np.any(box_max <= box_min):
        raise ScenarioError(f"{w}: box_max_mm must exceed box_min_mm on every axis")
    abc_min = _arr(cam_t, "abc_min_deg", w, (3,), [0.0] * 3)
    abc_max = _arr(cam_t, "abc_max_deg", w, (3,), [0.0] * 3)
    if np.any(abc_max < abc_min):
        raise ScenarioError(f"{w}: abc_max_deg must not be below abc_min_deg")
    home = _arr(cam_t, "home_deg", w, (6,))
    lim = robot.axis_limits_deg
    if np.any(home < lim[:, 0]) or np.any(home > lim[:, 1]):
        raise ScenarioError(f"{w}.home_deg: outside the axis limits of {robot.name}")
    payload = _arr(cam_t, "payload_kg", w, (len(cam_t.get("payload_kg", [0.0])),), [0.0], lo=0.0)
    if payload.size == 0:
        raise ScenarioError(f"{w}.payload_kg: give at least one payload")
    check_fraction = _num(cam_t, "check_fraction", w, 0.4, lo=0.0)
    if check_fraction >= 1.0:
        raise ScenarioError(f"{w}.check_fraction: must be below 1, got {check_fraction}")
    return CampaignSettings(
        box_min_mm=box_min,
        box_max_mm=box_max,
        abc_min_deg=abc_min,
        abc_max_deg=abc_max,
        home_deg=home,
        payload_kg=tuple(float(p) for p in payload),
        check_fraction=check_fraction,
        repeats=_count(cam_t, "repeats", w, 1, least=1),
        seed=_count(cam_t, "seed", w, 0, least=0),
        targets=_count(cam_t, "targets", w, 1, least=1),
    )


_TABLES = {"scenario", "geometric", "effects", "noise", "motion", "cell", "campaign"}


def parse_scenario_toml(text: str, source: str = "<string>") -> Scenario:
    """Parse and validate a scenario file's text."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: not valid TOML: {exc}") from None
    for key in doc:
        if key not in _TABLES:
            raise ScenarioError(f"{source}: unknown table [{key}] (allowed: {', '.join(sorted(_TABLES))})")
    name, description, robot, seed = _parse_header(doc, source)
    return Scenario(
        name=name,
        description=description,
        robot=robot,
        seed=seed,
        geometric=_parse_geometric(doc, source),
        effects=_parse_effects(doc, source),
        noise=_parse_noise(doc, source),
        motion=_parse_motion(doc, source),
        cell=_parse_cell(doc, source),
        campaign=_parse_campaign(doc, source, robot),
        source=source,
    )


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a preset scenario by name (:data:`PRESET_SCENARIOS`) or a scenario file by path."""
    key = str(name_or_path)
    if key in PRESET_SCENARIOS:
        text = resources.files("comp_daemon.sim").joinpath(f"scenarios/{key}.toml").read_text("utf-8")
        return parse_scenario_toml(text, source=f"preset:{key}")
    path = Path(key)
    if not path.is_file():
        raise ScenarioError(
            f"scenario '{key}': neither a preset ({', '.join(PRESET_SCENARIOS)}) nor a readable file"
        )
    try:
        text = path.read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: cannot read: {exc}") from None
    return parse_scenario_toml(text, source=str(path))
