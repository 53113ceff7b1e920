"""Grating calibration (seed 000, step 1): the map from a scale's position count to the joint angle.

A linear scale on a finished arc of radius ``radius_mm`` around the joint reads
``count * resolution_nm`` of arc length, so the joint angle in controller axis values (deg) is::

    angle_deg = count * slope_deg_per_count + zero_deg
    slope_deg_per_count = scale * (resolution_nm * 1e-6 / radius_mm) * 180 / pi

``scale`` absorbs the true radius and the mounting direction (negative when the count grows
against the axis direction); ``zero_deg`` is the angle at count 0. Both are fitted by linear least
squares from readings taken at standstill against the controller's axis values (``AIPos``) over
a spread of poses. Approaching each pose from both directions averages the joint backlash out of
``zero_deg``; what is left (half the backlash, gravity deflection, cyclic transmission error) shows
in the residual statistics, which are part of the artifact.

Artifacts are JSON (:meth:`GratingCalibration.to_json`), versioned by an integer that grows with
every new calibration, and load back bit-exact.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon import __version__
from comp_daemon.common.atomic import write_text_atomic

__all__ = [
    "ARTIFACT_KIND",
    "GratingCalibration",
    "GratingCalibrationError",
    "JointGratingMap",
    "build_calibration",
    "default_calibration_poses",
    "fit_joint_map",
    "load_calibration",
    "load_latest_calibration",
    "next_version",
    "nominal_slope_deg_per_count",
    "save_calibration",
]

ARTIFACT_KIND = "grating_calibration"
SCHEMA_VERSION = 1
_FILE_RE = re.compile(r"^grating-cal-v(\d{4,})\.json$")


class GratingCalibrationError(ValueError):
    """A calibration that cannot be fitted or an artifact that cannot be read; the message says why."""


def nominal_slope_deg_per_count(radius_mm: float, resolution_nm: float) -> float:
    """Degrees of joint rotation per count for a scale on an arc of ``radius_mm``."""
    return math.degrees(resolution_nm * 1e-6 / radius_mm)


@dataclass(frozen=True, slots=True)
class JointGratingMap:
    """The fitted map of one joint (``joint`` is 1-based: 1 = A1)."""

    joint: int
    radius_mm: float
    resolution_nm: float
    slope_deg_per_count: float
    zero_deg: float
    n_readings: int
    span_deg: float
    residual_rms_deg: float
    residual_max_deg: float

    @property
    def scale(self) -> float:
        """Fitted slope over the nominal one (1 for a scale of the stated radius, mounted forward)."""
        return self.slope_deg_per_count / nominal_slope_deg_per_count(self.radius_mm, self.resolution_nm)

    def angle_deg(self, count: int | float) -> float:
        """The joint angle (deg) for one position count; O(1), used every cycle."""
        return count * self.slope_deg_per_count + self.zero_deg


@dataclass(frozen=True, slots=True)
class GratingCalibration:
    """A versioned set of joint maps, one per grating."""

    version: int
    created_at: str
    joints: tuple[JointGratingMap, ...]
    library_version: str = __version__

    def for_joint(self, joint: int) -> JointGratingMap:
        for m in self.joints:
            if m.joint == joint:
                return m
        raise KeyError(f"grating calibration v{self.version} has no map for joint A{joint}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": ARTIFACT_KIND,
            "schema": SCHEMA_VERSION,
            "version": self.version,
            "created_at": self.created_at,
            "library_version": self.library_version,
            "joints": [asdict(m) for m in self.joints],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, allow_nan=False)

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> GratingCalibration:
        if not isinstance(doc, dict) or doc.get("kind") != ARTIFACT_KIND:
            raise GratingCalibrationError(f"not a {ARTIFACT_KIND} artifact (field 'kind')")
        if doc.get("schema") != SCHEMA_VERSION:
            raise GratingCalibrationError(
                f"unsupported schema {doc.get('schema')!r} (field 'schema'), expected {SCHEMA_VERSION}"
            )
        try:
            version = int(doc["version"])
            created_at = str(doc["created_at"])
            library_version = str(doc.get("library_version", ""))
            raw_joints = doc["joints"]
        except KeyError as exc:
            raise GratingCalibrationError(f"missing field {exc.args[0]!r}") from None
        if version < 1:
            raise GratingCalibrationError(f"field 'version' must be >= 1, got {version}")
        if not isinstance(raw_joints, list) or not raw_joints:
            raise GratingCalibrationError("field 'joints' must be a non-empty list")
        joints = []
        names = JointGratingMap.__dataclass_fields__.keys()
        for i, raw in enumerate(raw_joints):
            missing = [n for n in names if n not in raw]
            if missing:
                raise GratingCalibrationError(f"joints[{i}]: missing field {missing[0]!r}")
            m = JointGratingMap(
                joint=int(raw["joint"]),
                radius_mm=float(raw["radius_mm"]),
                resolution_nm=float(raw["resolution_nm"]),
                slope_deg_per_count=float(raw["slope_deg_per_count"]),
                zero_deg=float(raw["zero_deg"]),
                n_readings=int(raw["n_readings"]),
                span_deg=float(raw["span_deg"]),
                residual_rms_deg=float(raw["residual_rms_deg"]),
                residual_max_deg=float(raw["residual_max_deg"]),
            )
            if not 1 <= m.joint <= 6:
                raise GratingCalibrationError(f"joints[{i}]: field 'joint' must be 1..6, got {m.joint}")
            if not (math.isfinite(m.slope_deg_per_count) and m.slope_deg_per_count != 0.0):
                raise GratingCalibrationError(
                    f"joints[{i}]: field 'slope_deg_per_count' must be finite, non-zero"
                )
            joints.append(m)
        if len({m.joint for m in joints}) != len(joints):
            raise GratingCalibrationError("field 'joints' lists a joint twice")
        return cls(version, created_at, tuple(joints), library_version)

    @classmethod
    def from_json(cls, text: str) -> GratingCalibration:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise GratingCalibrationError(f"not JSON: {exc}") from None
        return cls.from_dict(doc)


def fit_joint_map(
    joint: int,
    counts: ArrayLike,
    axis_deg: ArrayLike,
    *,
    radius_mm: float,
    resolution_nm: float = 50.0,
    min_readings: int = 6,
    min_span_deg: float = 10.0,
    max_scale_deviation: float = 0.05,
) -> JointGratingMap:
    """Fit ``angle = count * slope + zero`` by least squares; refuse data that cannot determine it.

    ``counts`` and ``axis_deg`` are readings at standstill, one per pose (or per approach
    direction). Refused: fewer than ``min_readings`` readings, an axis span narrower than
    ``min_span_deg``, non-finite values, and a fitted slope whose magnitude differs from the nominal
    one (radius, resolution) by more than ``max_scale_deviation`` — a wrong radius, a scale slipping,
    or readings paired with the wrong joint.
    """
    c = np.asarray(counts, dtype=np.float64).reshape(-1)
    a = np.asarray(axis_deg, dtype=np.float64).reshape(-1)
    where = f"joint A{joint}"
    if c.shape != a.shape:
        raise GratingCalibrationError(f"{where}: {c.size} counts but {a.size} axis values")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
        bad = int(np.flatnonzero(~(np.isfinite(c) & np.isfinite(a)))[0])
        raise GratingCalibrationError(f"{where}: reading {bad} is not finite")
    if c.size < min_readings:
        raise GratingCalibrationError(f"{where}: {c.size} readings, at least {min_readings} needed")
    span = float(a.max() - a.min())
    if span < min_span_deg:
        raise GratingCalibrationError(
            f"{where}: the poses span {span:.3f} deg of the axis, at least {min_span_deg} deg needed"
        )
    if not (radius_mm > 0.0 and resolution_nm > 0.0):
        raise GratingCalibrationError(f"{where}: radius_mm and resolution_nm must be > 0")
    # centre the counts for conditioning (counts are ~1e7, slopes ~1e-6 deg)
    c0 = float(c.mean())
    design = np.column_stack([c - c0, np.ones_like(c)])
    coef, *_ = np.linalg.lstsq(design, a, rcond=None)
    slope = float(coef[0])
    zero = float(coef[1] - slope * c0)
    nominal = nominal_slope_deg_per_count(radius_mm, resolution_nm)
    scale = abs(slope) / nominal
    if abs(scale - 1.0) > max_scale_deviation:
        raise GratingCalibrationError(
            f"{where}: fitted scale {scale:.4f} differs from 1 by more than {max_scale_deviation} "
            f"(radius {radius_mm} mm, resolution {resolution_nm} nm) — wrong radius or wrong joint?"
        )
    residual = a - (design @ coef)
    return JointGratingMap(
        joint=joint,
        radius_mm=float(radius_mm),
        resolution_nm=float(resolution_nm),
        slope_deg_per_count=slope,
        zero_deg=zero,
        n_readings=int(c.size),
        span_deg=span,
        residual_rms_deg=float(np.sqrt(np.mean(residual**2))),
        residual_max_deg=float(np.max(np.abs(residual))),
    )


def save_calibration(directory: str | os.PathLike[str], calibration: GratingCalibration) -> Path:
    """Write ``grating-cal-v{version:04d}.json`` atomically; refuse to overwrite an existing version."""
    folder = Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"grating-cal-v{calibration.version:04d}.json"
    try:  # exclusive: fails also if another writer created the version meanwhile
        return write_text_atomic(path, calibration.to_json(), exclusive=True)
    except FileExistsError:
        raise GratingCalibrationError(f"{path} exists: calibration versions are never overwritten") from None


def load_calibration(path: str | os.PathLike[str]) -> GratingCalibration:
    p = Path(path)
    try:
        return GratingCalibration.from_json(p.read_text(encoding="utf-8"))
    except GratingCalibrationError as exc:
        raise GratingCalibrationError(f"{p}: {exc}") from None


def _versions(directory: Path) -> list[tuple[int, Path]]:
    if not directory.is_dir():
        return []
    found = []
    for p in directory.iterdir():
        m = _FILE_RE.match(p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found)


def load_latest_calibration(directory: str | os.PathLike[str]) -> GratingCalibration | None:
    """The highest version stored in ``directory``, or None when there is none."""
    versions = _versions(Path(directory))
    return load_calibration(versions[-1][1]) if versions else None


def next_version(directory: str | os.PathLike[str]) -> int:
    versions = _versions(Path(directory))
    return versions[-1][0] + 1 if versions else 1


def build_calibration(
    directory: str | os.PathLike[str], maps: Sequence[JointGratingMap], created_at: str
) -> GratingCalibration:
    """A new calibration with the next free version number in ``directory``."""
    return GratingCalibration(next_version(directory), created_at, tuple(sorted(maps, key=lambda m: m.joint)))


def default_calibration_poses(
    home_deg: Sequence[float],
    joints: Sequence[int],
    limits_deg: NDArray[np.float64],
    *,
    span_deg: float = 20.0,
    n: int = 6,
    margin_deg: float = 2.0,
) -> list[tuple[float, ...]]:
    """``n`` poses around ``home_deg`` that sweep every grating joint over ``±span_deg``.

    The joints sweep with different phases (so the poses do not lie on one line in joint space)
    and stay ``margin_deg`` inside the axis limits.
    """
    if n < 3:
        raise ValueError(f"need at least 3 calibration poses, got {n}")
    home = np.asarray(home_deg, dtype=float)
    poses = []
    for k in range(n):
        pose = home.copy()
        for i, j in enumerate(joints):
            phase = (k + i * (n // max(1, len(joints)))) % n
            frac = -1.0 + 2.0 * phase / (n - 1)
            lo, hi = limits_deg[j - 1, 0] + margin_deg, limits_deg[j - 1, 1] - margin_deg
            pose[j - 1] = float(np.clip(home[j - 1] + frac * span_deg, lo, hi))
        poses.append(tuple(float(v) for v in pose))
    return poses
