"""Model artifacts: one JSON document per fitted model, loaded back bit-exact.

Document (``format`` = ``comp-daemon-model``, ``format_version`` = 1)::

    kind            the model class's kind, a key of :data:`comp_daemon.models.registry.ARTIFACT_KINDS`
                    (the registry's model classes; ``GET /api/fits/kinds`` gives each kind's)
    order           Chebyshev order (null for the others)
    robot           {"name", "sha256", "description"}: the robot description the model belongs to,
                    embedded so that the artifact stands alone; its hash is RobotDescription.sha256
    frame           "base" | "tracker": the frame the fit data were measured in
    registration    4×4 robot base frame in the measurement frame (targets in the base frame map
                    through it)
    model           the kind's parameters / coefficients, by name (see each model's ``to_payload``)
    uncertainty     (parametric fits only) the fit's parameter covariance
                    (:meth:`comp_daemon.models.covariance.ParameterCovariance.to_dict`), which
                    gives the loaded model its ``predict_std_mm``
    data_sha256     hash of the fitted data (Dataset.content_sha256, or of the arrays fitted on)
    fit             fit statistics (rows, RMS, iterations, identifiability, selection, …)
    library_version comp_daemon.__version__
    created_utc     ISO 8601 time of writing
    checksum_sha256 SHA-256 of the canonical JSON of everything above

Floats are written by ``json`` as ``repr`` (the shortest text that reads back to the same double),
so a loaded model predicts bit for bit what the saved one did. Loading refuses, with a
:class:`ModelArtifactError` that says what is wrong: text that is not JSON, another format or
version, a missing or malformed field (named), a checksum that does not match (a corrupt or edited
file), an embedded robot description that does not match its hash, and — when the caller names the
robot — a model fitted for another robot.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon import __version__
from comp_daemon.common.atomic import write_text_atomic
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.covariance import ParameterCovariance
from comp_daemon.models.registry import ARTIFACT_KINDS, model_from_payload
from comp_daemon.robot.description import Joint, RobotDescription

__all__ = [
    "ARTIFACT_FORMAT",
    "ARTIFACT_VERSION",
    "LoadedModel",
    "ModelArtifactError",
    "arrays_sha256",
    "load_model",
    "model_document",
    "model_from_artifact",
    "parse_model",
    "save_model",
]

ARTIFACT_FORMAT = "comp-daemon-model"
ARTIFACT_VERSION = 1


class ModelArtifactError(ValueError):
    """A model file that cannot be used; the message names the file and the fault."""


@dataclass(frozen=True, slots=True)
class LoadedModel:
    model: ErrorModel
    document: dict[str, Any]

    @property
    def data_sha256(self) -> str:
        return str(self.document["data_sha256"])

    @property
    def frame(self) -> str:
        return str(self.document["frame"])


def arrays_sha256(*arrays: NDArray[Any] | None) -> str:
    """SHA-256 over arrays (dtype, shape and bytes of each; None counts as absent)."""
    h = hashlib.sha256()
    for arr in arrays:
        if arr is None:
            h.update(b"none;")
            continue
        a = np.ascontiguousarray(arr)
        h.update(f"{a.dtype.str}{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _json_ready(value: Any) -> Any:
    """Numbers, lists and dicts as plain JSON values; non-finite floats become null."""
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_ready(value.tolist())
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        return f if math.isfinite(f) else None
    return value


def _canonical(doc: dict[str, Any]) -> bytes:
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")


def model_document(
    model: ErrorModel,
    *,
    data_sha256: str,
    frame: str,
    fit: dict[str, Any] | None = None,
    created_utc: str | None = None,
) -> dict[str, Any]:
    """The artifact document of ``model`` (module docstring), checksum included."""
    if model.kind not in ARTIFACT_KINDS:
        raise ValueError(f"unknown model kind '{model.kind}'")
    if frame not in ("base", "tracker"):
        raise ValueError(f"frame must be 'base' or 'tracker', got {frame!r}")
    created = created_utc or _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    doc: dict[str, Any] = {
        "format": ARTIFACT_FORMAT,
        "format_version": ARTIFACT_VERSION,
        "kind": model.kind,
        "order": model.order,
        "robot": {
            "name": model.robot.name,
            "sha256": model.robot.sha256,
            "description": model.robot.to_dict(),
        },
        "frame": frame,
        "registration": model.registration.tolist(),
        "model": model.to_payload(),
        **({"uncertainty": model.uncertainty.to_dict()} if model.uncertainty is not None else {}),
        "data_sha256": data_sha256,
        "fit": _json_ready(fit or {}),
        "library_version": __version__,
        "created_utc": created,
    }
    doc["checksum_sha256"] = hashlib.sha256(_canonical(doc)).hexdigest()
    return doc


def save_model(
    model: ErrorModel,
    path: str | os.PathLike[str],
    *,
    data_sha256: str,
    frame: str,
    fit: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the artifact atomically (temporary file, then rename); returns the document."""
    doc = model_document(model, data_sha256=data_sha256, frame=frame, fit=fit)
    write_text_atomic(path, json.dumps(doc, indent=1, allow_nan=False) + "\n")
    return doc


def _field(doc: dict[str, Any], key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if key not in doc:
        raise ModelArtifactError(f"{where}: missing field '{key}'")
    value = doc[key]
    if not isinstance(value, kind):
        raise ModelArtifactError(f"{where}: field '{key}' has the wrong type ({type(value).__name__})")
    return value


def _robot_from_dict(desc: dict[str, Any], source: str) -> RobotDescription:
    robot = desc["robot"]
    joints = tuple(
        Joint(
            a_mm=float(j["a_mm"]),
            alpha_deg=float(j["alpha_deg"]),
            d_mm=float(j["d_mm"]),
            beta_deg=float(j["beta_deg"]),
            sign=int(j["sign"]),
            offset_deg=float(j["offset_deg"]),
            min_deg=float(j["min_deg"]),
            max_deg=float(j["max_deg"]),
            mass_kg=float(j["mass_kg"]),
            com_mm=(float(j["com_mm"][0]), float(j["com_mm"][1]), float(j["com_mm"][2])),
        )
        for j in desc["joint"]
    )
    if len(joints) != 6:
        raise ValueError(f"{len(joints)} joints")
    tool = desc["tool"]["xyz_mm"]
    return RobotDescription(
        name=str(robot["name"]),
        repeatability_mm=float(robot["repeatability_mm"]),
        tool_xyz_mm=(float(tool[0]), float(tool[1]), float(tool[2])),
        joints=joints,
        source=source,
    )


def parse_model(text: str, source: str = "<model>", robot: RobotDescription | None = None) -> LoadedModel:
    """A model from the text of an artifact; ``robot``, when given, must be the one it was fitted for."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ModelArtifactError(f"{source}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    if not isinstance(doc, dict):
        raise ModelArtifactError(f"{source}: not a model artifact (expected a JSON object)")
    if doc.get("format") != ARTIFACT_FORMAT:
        raise ModelArtifactError(f"{source}: not a comp-daemon model (format {doc.get('format')!r})")
    version = doc.get("format_version")
    if version != ARTIFACT_VERSION:
        raise ModelArtifactError(
            f"{source}: format_version {version!r} is not supported (expected {ARTIFACT_VERSION})"
        )
    checksum = _field(doc, "checksum_sha256", str, source)
    body = {k: v for k, v in doc.items() if k != "checksum_sha256"}
    try:
        actual = hashlib.sha256(_canonical(body)).hexdigest()
    except ValueError:
        actual = ""
    if actual != checksum:
        raise ModelArtifactError(f"{source}: checksum mismatch: the file is corrupt or was edited")
    kind = _field(doc, "kind", str, source)
    if kind not in ARTIFACT_KINDS:
        raise ModelArtifactError(
            f"{source}: unknown model kind '{kind}' (known: {', '.join(ARTIFACT_KINDS)})"
        )
    robot_doc = _field(doc, "robot", dict, source)
    recorded_sha = _field(robot_doc, "sha256", str, f"{source} robot")
    try:
        embedded = _robot_from_dict(
            _field(robot_doc, "description", dict, f"{source} robot"), f"model:{source}"
        )
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise ModelArtifactError(f"{source}: embedded robot description is malformed ({exc})") from None
    if embedded.sha256 != recorded_sha:
        raise ModelArtifactError(f"{source}: embedded robot description does not match its sha256")
    if robot is not None and robot.sha256 != recorded_sha:
        raise ModelArtifactError(
            f"{source}: model was fitted for robot '{embedded.name}' (sha256 {recorded_sha[:12]}…), "
            f"not for '{robot.name}' (sha256 {robot.sha256[:12]}…)"
        )
    order = doc.get("order")
    if order is not None and (not isinstance(order, int) or isinstance(order, bool) or order < 0):
        raise ModelArtifactError(f"{source}: field 'order' must be a non-negative integer or null")
    frame = _field(doc, "frame", str, source)
    if frame not in ("base", "tracker"):
        raise ModelArtifactError(f"{source}: field 'frame' must be 'base' or 'tracker'")
    _field(doc, "data_sha256", str, source)
    registration = np.array(_field(doc, "registration", list, source), dtype=float)
    if registration.shape != (4, 4) or not np.all(np.isfinite(registration)):
        raise ModelArtifactError(f"{source}: field 'registration' must be a finite 4×4 matrix")
    payload = _field(doc, "model", dict, source)
    try:
        model = model_from_payload(kind, embedded, payload, order, registration)
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelArtifactError(f"{source}: {kind} model content is malformed ({exc})") from None
    if "uncertainty" in doc:
        try:
            model.uncertainty = ParameterCovariance.from_dict(_field(doc, "uncertainty", dict, source))
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelArtifactError(f"{source}: field 'uncertainty' is malformed ({exc})") from None
    return LoadedModel(model=model, document=doc)


def load_model(path: str | os.PathLike[str], robot: RobotDescription | None = None) -> LoadedModel:
    """Read an artifact file (see :func:`parse_model`)."""
    try:
        text = Path(path).read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelArtifactError(f"{path}: cannot read: {exc}") from None
    return parse_model(text, source=str(path), robot=robot)


def model_from_artifact(artifact: Mapping[str, Any], robot: RobotDescription, where: str) -> ErrorModel:
    """The model of a stored artifact document (as fit jobs store it), for ``robot``.

    :class:`ModelArtifactError` naming ``where`` when the document is not a checksummed
    ``comp-daemon-model``, is damaged, or belongs to another robot.
    """
    if "checksum_sha256" not in artifact:
        raise ModelArtifactError(f"{where}: the stored artifact is not a comp-daemon model document")
    return parse_model(json.dumps(dict(artifact)), source=where, robot=robot).model
