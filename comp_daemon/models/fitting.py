"""What every kind's fit shares: its signature's types, the effect selection, the base calibration
they share, and the summaries of a fit.

Each kind's module (:mod:`comp_daemon.models.registry` lists them) has a fit function of one
signature, ``fit(robot, rows, spec, options) -> FittedModel``: ``rows`` are the measured rows
(:class:`~comp_daemon.models.rows.MeasuredRows`: axis values, TCP positions, and the optional
columns a kind may use), ``spec`` the parsed model name (:class:`ModelSpec`: kind, joint effects,
Chebyshev order, options), ``options`` the door's settings (:class:`FitOptions`: frame,
cross-validation folds and seed). The result holds the model, the frame the data were in and a
JSON-ready summary of the fit (rows, RMS, solver, identifiability, selection) built with
:func:`lm_info`, :func:`report_info`, :func:`identified_info` and, for a kinematic base,
:func:`kinematic_info`.

What earns its place. The joint effects of the kinematic, kriging and compliance kinds, a kriging
stage on its base and per-joint kriging ranges are kept only if they lower the error of held-out
predictions on the fit rows (:mod:`comp_daemon.estimation.selection`: K-fold cross-validation with
``options.cv_folds`` folds on at most :data:`SELECTION_MAX_ROWS` of them, or leave-one-out for the
kriging); the rest is dropped and the kind falls
back to what is left (a kriging kind whose kriging is dropped is its kinematic base). The summary's
``selection`` says what was kept and dropped and on what numbers. The ``all`` option
(``kinematic:all+ratio+backlash``, ``kriging-backlash:all``, ``compliance:all``) keeps every part, as
the papers do.

Several targets per pose (``x2, y2, z2`` … of the data set, ``MeasuredRows.more_xyz_mm``): the
kinematic calibration, and the kinematic base of both kriging kinds, identify every target's flange
offset with the rest and fit all targets' positions (6-DOF with three or more targets,
:mod:`comp_daemon.models.kinematic`); the model predicts, and every kind is judged on, the TCP (the
first target, ``x, y, z``). The other kinds (``nominal``, ``chebyshev``, ``compliance``, ``poe``)
and the kriging layer itself fit the TCP alone; the further targets are ignored there.

One calibration for several kinds. A kinematic kind and the kriging kinds built on it select and
calibrate the same base (``kinematic+ratio+backlash+compliance`` and ``kriging-backlash+compliance``,
``kinematic`` and ``kriging``): the last :data:`BASE_FITS_KEPT` base fits are kept, keyed by the
content of the robot description, the rows, the effects and the options, and a kind that asks for
one already made gets a copy of it (``evaluate --models all`` calibrates each base once). The copy
is the same fit to the last bit; :func:`forget_base_fits` empties the store.
"""

from __future__ import annotations

import copy
import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.identifiability import IdentifiabilityReport
from comp_daemon.estimation.lm import LMResult
from comp_daemon.estimation.registration import detect_frame
from comp_daemon.estimation.selection import Selection, keep_all, select_kinematic_effects
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.covariance import (
    ParameterCovariance,
    attach_covariance,
    covariance_from_fit,
    near_dependent_pairs,
)
from comp_daemon.models.kinematic import KinematicFit, calibrate_kinematic
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "FitOptions",
    "FittedModel",
    "ModelSpec",
    "attach_tcp_covariance",
    "forget_base_fits",
    "identified_info",
    "kinematic_info",
    "lm_info",
    "report_info",
    "rms_mm",
    "select_effects",
    "selected_base",
]

SELECTION_MAX_ROWS = 2000  # effects are selected on at most this many fit rows, drawn at random
#: the cross-validation folds of a selection skip what only a reported fit needs (the identifiability
#: report's rank checks): the same kept parts and held-out errors, at less cost; False runs every fold
#: as a full fit (the reference the tests compare with)
FOLD_SHORTCUTS = True
BASE_FITS_KEPT = 4  # base calibrations kept for the kinds that share them (module docstring)
FrameChoice = Literal["auto", "base", "tracker"]
#: identified parameters that are not the robot's: further targets, stations' frames, the probe's mount
NOT_THE_ROBOT = ("target", "station_", "probe_")


@dataclass(frozen=True, slots=True)
class ModelSpec:
    """A parsed model name: ``kinematic+ratio+backlash``, ``chebyshev:3``, ``chebyshev:cv``, …"""

    kind: str
    effects: tuple[str, ...] = ()
    order: int | None = None  # Chebyshev order; None: the kind's default
    order_by_cv: bool = False  # Chebyshev: choose the order by cross-validation
    options: tuple[str, ...] = ()  # kriging: "k=64" (local neighbourhoods), "aniso" (per-joint ranges)

    @property
    def name(self) -> str:
        """The canonical model name (what :func:`comp_daemon.models.registry.parse_model_name` reads)."""
        head = self.kind
        if self.order_by_cv:
            head += ":cv"
        elif self.order is not None:
            head += f":{self.order}"
        head += "".join(f":{o}" for o in self.options)
        return "+".join([head, *self.effects])

    @property
    def neighbours(self) -> int | None:
        """The ``k=N`` option (kriging in local neighbourhoods of N samples), or None."""
        for o in self.options:
            if o.startswith("k="):
                return int(o[2:])
        return None

    @property
    def anisotropic(self) -> bool:
        """The ``aniso`` option: kriging with per-joint ranges."""
        return "aniso" in self.options

    @property
    def keep_all(self) -> bool:
        """The ``all`` option: every effect kept as named, no selection (the papers' forms)."""
        return "all" in self.options

    @property
    def paper(self) -> bool:
        """The ``paper`` option: the paper's own form of the kind (``compliance:paper``, seed 004)."""
        return "paper" in self.options


@dataclass(frozen=True, slots=True)
class FitOptions:
    """Settings of a fit that are not part of the model name."""

    frame: FrameChoice = "auto"
    cv_folds: int = 5
    seed: int = 0


@dataclass(frozen=True, slots=True)
class FittedModel:
    model: ErrorModel
    frame: Literal["base", "tracker"]
    info: dict[str, Any]


def lm_info(lm: LMResult) -> dict[str, Any]:
    return {
        "method": "improved Levenberg-Marquardt (seed 000)",
        "iterations": lm.iterations,
        "converged": lm.converged,
        "stop": lm.reason,
        "residual_evaluations": lm.n_residual_evals,
        "jacobian_evaluations": lm.n_jacobian_evals,
        "time_s": lm.time_s,
        "final_cost_mm2": lm.cost,
    }


def report_info(report: IdentifiabilityReport, list_removed: bool = True) -> dict[str, Any]:
    out: dict[str, Any] = {
        "candidates": len(report.candidates),
        "identifiable": len(report.identifiable),
        "rank_qr": report.rank_qr,
        "rank_svd": report.rank_svd,
        "condition_number": report.condition_number,
    }
    if list_removed:
        out["removed"] = [
            {
                "name": r.name,
                "reason": r.reason,
                "depends_on": list(r.depends_on),
                "coefficients": list(r.coefficients),
            }
            for r in report.removed
        ]
    else:
        out["removed"] = [r.name for r in report.removed]
    return out


def identified_info(
    names: Sequence[str], values: NDArray[np.float64], std: NDArray[np.float64]
) -> dict[str, Any]:
    return {n: {"value": float(v), "std": float(s)} for n, v, s in zip(names, values, std, strict=True)}


def rms_mm(model: ErrorModel, rows: MeasuredRows) -> float:
    err = model.predict_tcp_mm(rows.a_deg, rows.dir, rows.payload_kg, rows.temp_c) - rows.xyz_mm
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _kinematic(
    robot: RobotDescription,
    rows: MeasuredRows,
    effects: Sequence[str],
    options: FitOptions,
    *,
    report_ranks: bool = True,
) -> KinematicFit:
    return calibrate_kinematic(
        robot,
        rows.a_deg,
        rows.xyz_mm,
        dir=rows.dir,
        payload_kg=rows.payload_kg,
        temp_c=rows.temp_c,
        effects=effects,
        frame=options.frame,
        more_targets_mm=rows.more_xyz_mm,
        sigma_mm=rows.sigma_mm,
        report_ranks=report_ranks,
        station=rows.station,
        station_names=rows.station_names,
        probe_r=rows.probe_r,
        probe_sigma_deg=rows.probe_sigma_deg,
    )


def attach_tcp_covariance(kf: KinematicFit) -> None:
    """The parameter covariance of the TCP's prediction: with several targets, the block of the
    geometric and effect parameters of the whole fit (the targets' offsets, the stations' frames
    and the probe's rotation on the flange do not move the TCP)."""
    if kf.targets == 1 and not any(name.startswith(NOT_THE_ROBOT) for name in kf.identified):
        attach_covariance(kf.model, kf.identified, kf.values, kf.lm.jacobian, kf.lm.residual)
        return
    jac = kf.lm.jacobian
    if jac.shape[0] <= jac.shape[1]:
        return
    cov, s = covariance_from_fit(jac, kf.lm.residual)
    keep = np.array([not name.startswith(NOT_THE_ROBOT) for name in kf.identified])
    kf.model.uncertainty = ParameterCovariance(
        tuple(n for n, k in zip(kf.identified, keep, strict=True) if k),
        kf.values[keep],
        cov[np.ix_(keep, keep)],
        s,
        kf.n_rows,
    )


def kinematic_info(kf: KinematicFit, effects: Sequence[str]) -> dict[str, Any]:
    targets: dict[str, Any] = {}
    if kf.targets > 1:
        assert kf.model.more_targets_mm is not None
        targets = {
            "targets": kf.targets,
            "identification": "6-DOF: every target's position"
            if kf.targets >= 3
            else "every target's position",
            "targets_rms_mm": kf.targets_rms_mm,
            "more_targets_mm": kf.model.more_targets_mm.tolist(),
        }
    weighting = {"weighting": "rows weighted by 1/sigma_mm (weighted least squares)"} if kf.weighted else {}
    observed: dict[str, Any] = {}
    if kf.stations:
        observed["stations"] = {
            "registration": "each station's frame estimated jointly with the robot's parameters "
            "(6 parameters per station beside the largest)",
            "moved": {
                name: {"angle_deg": _angle_deg(t), "shift_mm": float(np.linalg.norm(t[:3, 3]))}
                for name, t in kf.stations.items()
            },
        }
    if kf.orientation_rms_deg is not None:
        observed["orientation"] = {
            "observed": "6-DOF probe: orientation residuals weighted against the positions by the "
            "declared sigmas",
            "weight_mm_per_rad": kf.orientation_weight,
            "rms_deg": kf.orientation_rms_deg,
        }
    return {
        "rms_mm": kf.rms_mm,
        **targets,
        **weighting,
        **observed,
        "effects": list(effects),
        "solver": lm_info(kf.lm),
        "identifiability": {**report_info(kf.report), "near_dependent": _near_dependent(kf)},
        "identified": identified_info(kf.identified, kf.values, kf.std),
    }


def _near_dependent(kf: KinematicFit) -> list[dict[str, Any]]:
    """The identified parameters' near-dependent pairs (covariance of the fit at its solution);
    pairs inside the measurement frame (``base_*`` with ``base_*``) are left out: its translation
    and rotation correlate whenever the tracker's origin is far from the robot, and that frame is
    not the robot's."""
    try:
        cov, _ = covariance_from_fit(kf.lm.jacobian, kf.lm.residual)
    except ValueError:  # no more residuals than parameters: no covariance
        return []
    pairs = near_dependent_pairs(kf.identified, cov)
    frame = ("base_", "station_")
    return [p for p in pairs if not all(name.startswith(frame) for name in p["pair"])]


def _angle_deg(t: NDArray[np.float64]) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(t[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def _data_frame(
    robot: RobotDescription, rows: MeasuredRows, options: FitOptions
) -> Literal["base", "tracker"]:
    """The frame of the measured positions: ``options.frame``, or detected on every row."""
    if options.frame != "auto":
        return options.frame
    nominal = KinematicParams.from_robot(robot)
    return detect_frame(tcp_position_mm(nominal, axes_deg_to_q_rad(rows.a_deg, nominal.sign)), rows.xyz_mm)


def select_effects(
    robot: RobotDescription,
    rows: MeasuredRows,
    spec: ModelSpec,
    options: FitOptions,
    effects: Sequence[str],
    fit_on: Callable[[Sequence[str], MeasuredRows, FitOptions], ErrorModel] | None = None,
) -> tuple[tuple[str, ...], Selection]:
    """The ``effects`` that earn their place on the fit rows (:mod:`comp_daemon.estimation.selection`),
    every one of them with the spec's ``all`` option. ``fit_on(effects, rows, options)`` fits the
    model with those effects (default: the kinematic calibration)."""
    if not effects:
        return (), Selection((), (), ())
    if spec.keep_all:
        return tuple(effects), keep_all(effects)
    fold_options = FitOptions(_data_frame(robot, rows, options), options.cv_folds, options.seed)

    def kinematic_on(effs: Sequence[str], sub: MeasuredRows, fo: FitOptions) -> ErrorModel:
        return _kinematic(robot, sub, effs, fo, report_ranks=not FOLD_SHORTCUTS).model

    fit = fit_on or kinematic_on
    sub = rows
    if rows.n > SELECTION_MAX_ROWS:  # enough to show any effect worth its parameters
        pick = np.random.default_rng(options.seed).choice(rows.n, SELECTION_MAX_ROWS, replace=False)
        sub = rows.take(np.sort(pick))
    try:
        return select_kinematic_effects(
            effects,
            sub.n,
            lambda effs, idx: fit(effs, sub.take(idx), fold_options),
            lambda model, idx: sub.take(idx).errors(model),
            folds=options.cv_folds,
            seed=options.seed,
            of_rows=rows.n,
        )
    except (ValueError, np.linalg.LinAlgError) as exc:
        note = f"no selection: a cross-validation fit failed ({exc}); every effect kept"
        return tuple(effects), Selection(tuple(effects), (), (), note)


_BaseFit = tuple[tuple[str, ...], Selection, KinematicFit]
_base_fits: OrderedDict[str, _BaseFit] = OrderedDict()
_base_fits_lock = threading.Lock()


def forget_base_fits() -> None:
    """Empty the store of base calibrations (module docstring)."""
    with _base_fits_lock:
        _base_fits.clear()


def _base_key(
    robot: RobotDescription,
    rows: MeasuredRows,
    keep_all_effects: bool,
    options: FitOptions,
    effects: Sequence[str],
) -> str:
    """What a selected base calibration depends on, hashed: the robot's content, every column of
    the rows, the effects, ``all``, the options and the selection's settings."""
    h = hashlib.blake2b(digest_size=20)
    settings = (
        robot.sha256,
        tuple(effects),
        keep_all_effects,
        options,
        FOLD_SHORTCUTS,
        SELECTION_MAX_ROWS,
        rows.station_names,
        rows.probe_sigma_deg,
    )
    h.update(repr(settings).encode())
    columns = (
        rows.a_deg,
        rows.xyz_mm,
        rows.dir,
        rows.payload_kg,
        rows.temp_c,
        rows.more_xyz_mm,
        rows.sigma_mm,
        rows.station,
        rows.probe_r,
    )
    for col in columns:
        if col is None:
            h.update(b"none")
            continue
        arr = np.ascontiguousarray(col, dtype=float)
        h.update(repr(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def selected_base(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions, effects: Sequence[str]
) -> _BaseFit:
    """The ``effects`` that earn their place (:func:`select_effects`) and the calibration with
    them, made once for every kind that asks for the same (module docstring); the caller gets its
    own copy."""
    key = _base_key(robot, rows, spec.keep_all, options, effects)
    with _base_fits_lock:
        kept = _base_fits.get(key)
        if kept is not None:
            _base_fits.move_to_end(key)
    if kept is None:
        chosen, selection = select_effects(robot, rows, spec, options, effects)
        kept = (chosen, selection, _kinematic(robot, rows, chosen, options))
        with _base_fits_lock:
            _base_fits[key] = copy.deepcopy(kept)
            while len(_base_fits) > BASE_FITS_KEPT:
                _base_fits.popitem(last=False)
        return kept
    return copy.deepcopy(kept)
