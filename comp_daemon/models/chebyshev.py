"""The Chebyshev error model of seed 000 (§2.1): an error transfer matrix after every link frame.

Model (seed 000 eqs 7–11). The actual TCP is the nominal chain with an error transfer matrix
``E_i(theta_i)`` inserted after every link frame::

    world_T_tcp = world_T_base · E_0 · Π_{i=1..6} ( T_{i-1,i}(theta_i) · E_i(theta_i) ) · tool

    E_i = | 1      −eps_z   eps_y   delta_x |      (the differential transformation of seed 000
          | eps_z   1      −eps_x   delta_y |       eq. 8: three rotations eps (rad) about x, y, z
          | −eps_y  eps_x   1       delta_z |       of frame i and three translations delta (mm)
          | 0       0       0       1       |       along them)

and every differential term of link i is an order-m Chebyshev series of joint i's angle (eq. 10)::

    term_i(theta_i) = Σ_{k=0..m} lambda_{i,term,k} · c_k(x_i),   c_0 = 1, c_1 = x, c_k = 2x·c_{k−1} − c_{k−2}
    x_i = (2·A_i − (hi_i + lo_i)) / (hi_i − lo_i) ∈ [−1, 1]

``A_i`` is the commanded axis value (deg) and ``[lo_i, hi_i]`` the *joint's motion range in the
sampling campaign* (seed 000, Table 1 and step 2 of §2.3: "determine the motion range of each joint
… and generate sampling and target points in this range"), stored with the model. Outside that
range ``x`` is clipped to ±1 (the error is held at its value at the edge rather than extrapolated by
a polynomial). ``range_source="limits"`` maps over the robot's axis limits instead.

The order-0 terms are the geometric (constant) errors, the higher ones the joint-angle dependent
non-geometric errors (seed 000). ``E_0`` is a constant (order 0) error of the base frame, so that the
registration of a tracker frame is refined like the base frame of a kinematic calibration; the tool
error is the order-0 translation of ``E_6``.

The model is affine in the entries of each ``E_i``, so its Jacobian w.r.t. the coefficients
(seed 000 eq. 12) is exact: ``dp/dlambda = L_i · G_term · s_i · c_k(x_i)`` with ``L_i`` the linear part
of the chain up to ``E_i``, ``s_i`` the TCP in the coordinates after ``E_i`` and ``G_term`` the
generator of the term.

Coefficient names: ``E{i}.{term}.c{k}``, e.g. ``E3.eps_x.c2``; terms ``eps_x, eps_y, eps_z`` (rad)
and ``delta_x, delta_y, delta_z`` (mm).

Identification: the improved Levenberg–Marquardt method of seed 000
(:func:`comp_daemon.estimation.lm.improved_lm`) on the coefficients the data can identify;
coefficients with a zero or (numerically) dependent column in the Jacobian — identifiability
analysis of seed 003 on the Chebyshev Jacobian — are *removed* (held at zero), never regularised.
The order is chosen by k-fold cross-validation on the fit rows.

The kind (``KIND``): ``chebyshev`` fits order 3 (seed 000's), ``chebyshev:m`` order m,
``chebyshev:cv`` the order and the removal threshold chosen by k-fold cross-validation on the rows
given (:func:`select_order`; the fit's summary says what was chosen).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation import steps
from comp_daemon.estimation.identifiability import IdentifiabilityReport, analyze_identifiability
from comp_daemon.estimation.lm import LMResult, improved_lm
from comp_daemon.estimation.registration import detect_frame
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.base import ErrorModel, Query, StoredModel, as_axes, measured_positions
from comp_daemon.models.covariance import attach_covariance
from comp_daemon.models.fitting import FitOptions, FittedModel, ModelSpec, lm_info, report_info
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.kinematic import registered_start
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "CHEBYSHEV_RTOL",
    "DEFAULT_CHEBYSHEV_ORDER",
    "KIND",
    "TERMS",
    "ChebyshevFit",
    "ChebyshevModel",
    "ChebyshevProblem",
    "ChebyshevSetup",
    "OrderSelection",
    "chebyshev_basis",
    "chebyshev_identifiability",
    "chebyshev_jacobian",
    "chebyshev_parameters",
    "chebyshev_setup",
    "chebyshev_tcp_mm",
    "coefficient_names",
    "fit_chebyshev",
    "fit_chebyshev_kind",
    "link_transforms",
    "motion_range_deg",
    "n_coefficients",
    "select_order",
]

TERMS: tuple[str, ...] = ("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z")
N_LINKS = 7  # E_0 (base) and E_1 … E_6
DEFAULT_CHEBYSHEV_ORDER = 3  # seed 000 fits m = 3
CHEBYSHEV_RTOL = 0.2  # higher-order coefficients: kept if >= 20 % of the scaled column is new
CV_ORDERS: tuple[int, ...] = (0, 1, 2, 3, 4)
CV_RTOLS: tuple[float, ...] = (0.2, 0.1)
GEOMETRIC_RTOL = 1e-8  # order-0 (geometric) coefficients: only exact dependencies are removed
FrameChoice = Literal["auto", "base", "tracker"]
RangeSource = Literal["data", "limits"]

# generators: d E / d term (linear part), as the 3x3 matrices acting on the point, and translations
_GEN_ROT = np.zeros((3, 3, 3))
for _k in range(3):
    _e = np.zeros(3)
    _e[_k] = 1.0
    _GEN_ROT[_k] = np.array([[0.0, -_e[2], _e[1]], [_e[2], 0.0, -_e[0]], [-_e[1], _e[0], 0.0]])


def coefficient_names(order: int) -> tuple[str, ...]:
    """Names of all coefficients of an order-``order`` model, in the vector layout of this module.

    Layout: ``E0`` (6 terms, order 0), then for links 1..6, for each term, orders 0..m.
    """
    names = [f"E0.{t}.c0" for t in TERMS]
    for i in range(1, 7):
        for t in TERMS:
            names += [f"E{i}.{t}.c{k}" for k in range(order + 1)]
    return tuple(names)


def n_coefficients(order: int) -> int:
    return 6 + 36 * (order + 1)


def chebyshev_basis(x: NDArray[np.float64], order: int) -> NDArray[np.float64]:
    """(…, order+1) Chebyshev polynomials c_0..c_m of the first kind at ``x``."""
    x = np.asarray(x, dtype=float)
    out = np.empty((*x.shape, order + 1))
    out[..., 0] = 1.0
    if order >= 1:
        out[..., 1] = x
    for k in range(2, order + 1):
        out[..., k] = 2.0 * x * out[..., k - 1] - out[..., k - 2]
    return out


def link_transforms(params: KinematicParams, q_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 6, 4, 4) nominal link transforms ``T_{i-1,i}`` (MDH, :mod:`comp_daemon.kinematics.params`)."""
    theta = q_rad + params.theta_offset_rad
    c, s = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(params.alpha_rad), np.sin(params.alpha_rad)
    cb, sb = np.cos(params.beta_rad), np.sin(params.beta_rad)
    # M = Rx(alpha) Ry(beta) per joint, (6, 3, 3)
    m = np.zeros((6, 3, 3))
    m[:, 0, 0], m[:, 0, 2] = cb, sb
    m[:, 1, 0], m[:, 1, 1], m[:, 1, 2] = sa * sb, ca, -sa * cb
    m[:, 2, 0], m[:, 2, 1], m[:, 2, 2] = -ca * sb, sa, ca * cb
    n = q_rad.shape[0]
    out = np.zeros((n, 6, 4, 4))
    out[:, :, 0, :3] = c[..., None] * m[None, :, 0] - s[..., None] * m[None, :, 1]
    out[:, :, 1, :3] = s[..., None] * m[None, :, 0] + c[..., None] * m[None, :, 1]
    out[:, :, 2, :3] = np.broadcast_to(m[:, 2], (n, 6, 3))
    out[:, :, 0, 3] = params.a_mm * c
    out[:, :, 1, 3] = params.a_mm * s
    out[:, :, 2, 3] = params.d_mm
    out[:, :, 3, 3] = 1.0
    return out


def _map_axes(a_deg: NDArray[np.float64], range_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    lo, hi = range_deg[:, 0], range_deg[:, 1]
    return np.clip((2.0 * a_deg - (hi + lo)) / (hi - lo), -1.0, 1.0)


def _unpack(coef: NDArray[np.float64], order: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Vector → (6,) base terms and (6 links, 6 terms, m+1) series coefficients."""
    return coef[:6], coef[6:].reshape(6, 6, order + 1)


def _terms(coef: NDArray[np.float64], order: int, basis: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 7, 6) differential terms of E_0..E_6 at every pose."""
    base, series = _unpack(coef, order)
    n = basis.shape[0]
    out = np.empty((n, N_LINKS, 6))
    out[:, 0] = base
    # per link: (n, m+1) basis · (m+1, 6) coefficients
    np.matmul(basis.transpose(1, 0, 2), series.transpose(0, 2, 1), out=out[:, 1:].transpose(1, 0, 2))
    return out


# E − I as a linear map of the six terms, flat row-major 4 x 4: (0, 1) −eps_z, (0, 2) eps_y,
# (1, 0) eps_z, (1, 2) −eps_x, (2, 0) −eps_y, (2, 1) eps_x, and the translation (0..2, 3)
_TERMS_TO_E = np.zeros((6, 16))
for _entry, _term, _sign in ((1, 2, -1.0), (2, 1, 1.0), (4, 2, 1.0), (6, 0, -1.0), (8, 1, -1.0), (9, 0, 1.0)):
    _TERMS_TO_E[_term, _entry] = _sign
_TERMS_TO_E[3, 3] = _TERMS_TO_E[4, 7] = _TERMS_TO_E[5, 11] = 1.0
_IDENTITY_FLAT = np.eye(4).reshape(16)


def _error_matrices(terms: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 7, 4, 4) E = I + Δ from the (n, 7, 6) terms (eps_x, eps_y, eps_z, delta_x, delta_y, delta_z)."""
    # each entry is one term times ±1 (or 0): the product is exact, whatever the summation order
    e = terms @ _TERMS_TO_E
    e += _IDENTITY_FLAT
    return e.reshape(*terms.shape[:-1], 4, 4)


@dataclass(frozen=True, slots=True)
class ChebyshevSetup:
    """What does not change while the coefficients are iterated: links, basis, frame."""

    links: NDArray[np.float64]  # (n, 6, 4, 4)
    basis: NDArray[np.float64]  # (n, 6, m+1)
    world_T_base: NDArray[np.float64]
    tool_xyz_mm: NDArray[np.float64]
    order: int


def chebyshev_setup(
    params: KinematicParams, a_deg: NDArray[np.float64], range_deg: NDArray[np.float64], order: int
) -> ChebyshevSetup:
    q = axes_deg_to_q_rad(a_deg, params.sign)
    return ChebyshevSetup(
        links=link_transforms(params, q),
        basis=chebyshev_basis(_map_axes(a_deg, range_deg), order),
        world_T_base=params.world_T_base,
        tool_xyz_mm=params.tool_xyz_mm,
        order=order,
    )


def _forward(
    st: ChebyshevSetup, coef: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """TCP (n, 3) and E matrices (n, 7, 4, 4)."""
    e = _error_matrices(_terms(coef, st.order, st.basis))
    m = st.world_T_base @ e[:, 0]
    for i in range(6):
        m = m @ st.links[:, i] @ e[:, i + 1]
    return m[:, :3, :3] @ st.tool_xyz_mm + m[:, :3, 3], e


def _jacobian(
    st: ChebyshevSetup, coef: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """TCP (n, 3) and (n, 3, n_coefficients) d TCP / d coefficients, exact."""
    e = _error_matrices(_terms(coef, st.order, st.basis))
    n = st.basis.shape[0]
    # prefixes: linear part of the chain before each E_i (i = 0..6)
    pre = np.empty((n, N_LINKS, 4, 4))
    pre[:, 0] = st.world_T_base
    m = st.world_T_base @ e[:, 0]
    for i in range(6):
        pre[:, i + 1] = m @ st.links[:, i]
        m = pre[:, i + 1] @ e[:, i + 1]
    tcp = m[:, :3, :3] @ st.tool_xyz_mm + m[:, :3, 3]
    # suffixes: the TCP in the coordinates right after E_i
    suf = np.empty((n, N_LINKS, 3))
    s = np.broadcast_to(st.tool_xyz_mm, (n, 3)).copy()
    suf[:, 6] = s
    for i in range(6, 0, -1):
        t = st.links[:, i - 1] @ e[:, i]
        s = np.einsum("nij,nj->ni", t[:, :3, :3], s) + t[:, :3, 3]
        suf[:, i - 1] = s
    lin = pre[:, :, :3, :3]  # (n, 7, 3, 3)
    d_rot = np.einsum("kij,nlj->nlik", _GEN_ROT, suf)  # (n, 7, 3, 3): column k = e_k × s
    d_world = np.empty((n, N_LINKS, 3, 6))  # lin · [d_rot | I]
    np.matmul(lin, d_rot, out=d_world[..., :3])
    d_world[..., 3:] = lin
    jac = np.empty((n, 3, n_coefficients(st.order)))
    jac[:, :, :6] = d_world[:, 0]
    # the series columns (link, term, order) of each TCP coordinate, written in place
    series = jac[:, :, 6:].reshape(n, 3, 6, 6, st.order + 1)
    np.multiply(d_world[:, 1:].transpose(0, 2, 1, 3)[..., None], st.basis[:, None, :, None, :], out=series)
    return tcp, jac


def chebyshev_tcp_mm(
    params: KinematicParams,
    a_deg: NDArray[np.float64],
    range_deg: NDArray[np.float64],
    order: int,
    coef: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(n, 3) TCP of the Chebyshev error model (module docstring) at axis values ``a_deg`` (n, 6)."""
    return _forward(chebyshev_setup(params, as_axes(a_deg), range_deg, order), np.asarray(coef, dtype=float))[
        0
    ]


def chebyshev_jacobian(
    params: KinematicParams,
    a_deg: NDArray[np.float64],
    range_deg: NDArray[np.float64],
    order: int,
    coef: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(n, 3, n_coefficients) derivative of :func:`chebyshev_tcp_mm` w.r.t. the coefficients."""
    return _jacobian(
        chebyshev_setup(params, as_axes(a_deg), range_deg, order), np.asarray(coef, dtype=float)
    )[1]


class ChebyshevModel(ErrorModel):
    """Nominal geometry plus Chebyshev error transfer matrices (module docstring)."""

    kind: ClassVar[str] = "chebyshev"

    def __init__(
        self,
        robot: RobotDescription,
        world_T_base: NDArray[np.float64],
        order: int,
        range_deg: NDArray[np.float64],
        coefficients: NDArray[np.float64],
        active: NDArray[np.bool_] | None = None,
    ) -> None:
        if order < 0:
            raise ValueError(f"Chebyshev order must be >= 0, got {order}")
        coef = np.array(coefficients, dtype=float)
        if coef.shape != (n_coefficients(order),):
            raise ValueError(f"order {order} needs {n_coefficients(order)} coefficients, got {coef.shape}")
        rng = np.array(range_deg, dtype=float)
        if rng.shape != (6, 2) or np.any(rng[:, 1] <= rng[:, 0]):
            raise ValueError("range_deg must be (6, 2) with low < high for every joint")
        self.robot = robot
        self.world_T_base = np.array(world_T_base, dtype=float)
        self.registration = self.world_T_base
        self._order = int(order)
        self.range_deg = rng
        self.coefficients = coef
        self.active = np.ones(coef.size, bool) if active is None else np.array(active, dtype=bool)
        self._params = KinematicParams.from_robot(robot).with_base(self.world_T_base)

    @property
    def order(self) -> int:
        return self._order

    @property
    def names(self) -> tuple[str, ...]:
        return coefficient_names(self._order)

    def tcp_mm(self, query: Query) -> NDArray[np.float64]:
        return chebyshev_tcp_mm(self._params, query.a, self.range_deg, self._order, self.coefficients)

    def parameter_jacobian(
        self, names: Sequence[str], values: NDArray[np.float64], query: Query
    ) -> NDArray[np.float64]:
        """The model is affine in its coefficients: the exact Jacobian of the named ones."""
        index = {nm: i for i, nm in enumerate(self.names)}
        cols = np.array([index[nm] for nm in names], dtype=np.intp)
        jac = chebyshev_jacobian(self.ik_params(), query.a, self.range_deg, self.order, self.coefficients)
        return jac[:, :, cols]

    def outside_range(self, a_deg: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(n,) True where some axis value lies outside the fitted range (the error is held there)."""
        a = as_axes(a_deg)
        return np.any((a < self.range_deg[:, 0]) | (a > self.range_deg[:, 1]), axis=1)

    def ik_params(self) -> KinematicParams:
        return self._params

    def to_payload(self) -> dict[str, Any]:
        return {
            "range_deg": self.range_deg.tolist(),
            "coefficients": {n: float(c) for n, c in zip(self.names, self.coefficients, strict=True)},
            "removed": [n for n, a in zip(self.names, self.active, strict=True) if not a],
        }

    @classmethod
    def from_stored(cls, stored: StoredModel) -> ChebyshevModel:
        robot, payload, order = stored.robot, stored.payload, stored.order
        if order is None:
            raise ValueError("a Chebyshev model needs its order")
        names = coefficient_names(order)
        coef_map = payload["coefficients"]
        if not isinstance(coef_map, dict) or set(coef_map) != set(names):
            raise ValueError(
                f"model field 'coefficients': expected the {len(names)} names of an order-{order} model"
            )
        coef = np.array([float(coef_map[n]) for n in names])
        removed = set(payload.get("removed", []))
        active = np.array([n not in removed for n in names])
        return cls(
            robot, stored.registration, order, np.array(payload["range_deg"], dtype=float), coef, active
        )


class ChebyshevProblem:
    """Residual (predicted − measured, mm, (3n,)) and exact Jacobian over the coefficients ``active_idx``.

    The other coefficients are held at zero. Built on :func:`chebyshev_setup` of the fit rows.
    """

    def __init__(
        self, setup: ChebyshevSetup, active_idx: NDArray[np.intp], p_measured_mm: NDArray[np.float64]
    ):
        self.setup = setup
        self.idx = np.asarray(active_idx, dtype=np.intp)
        self.p_meas = p_measured_mm
        self.n_all = n_coefficients(setup.order)

    def full(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        c = np.zeros(self.n_all)
        c[self.idx] = x
        return c

    def residual(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return (_forward(self.setup, self.full(x))[0] - self.p_meas).reshape(-1)

    def jacobian(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return _jacobian(self.setup, self.full(x))[1][:, :, self.idx].reshape(-1, self.idx.size)


@dataclass(frozen=True, slots=True)
class ChebyshevFit:
    model: ChebyshevModel
    frame: Literal["base", "tracker"]
    report: IdentifiabilityReport
    lm: LMResult
    rms_mm: float
    n_rows: int
    selection: OrderSelection | None = None


@dataclass(frozen=True, slots=True)
class OrderSelection:
    """k-fold cross-validation: mean held-out 3-D RMS error (mm) per order and removal threshold."""

    orders: tuple[int, ...]
    rtols: tuple[float, ...]
    cv_rms_mm: tuple[tuple[float, ...], ...]  # [order][rtol]
    folds: int
    order: int
    rtol: float


def motion_range_deg(a_deg: NDArray[np.float64], min_span_deg: float = 1.0) -> NDArray[np.float64]:
    """(6, 2) motion range of every joint in the data (widened to ``min_span_deg`` if narrower)."""
    lo, hi = a_deg.min(axis=0), a_deg.max(axis=0)
    mid, half = (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, min_span_deg / 2.0)
    return np.stack(
        [
            np.where(hi - lo >= min_span_deg, lo, mid - half),
            np.where(hi - lo >= min_span_deg, hi, mid + half),
        ],
        axis=1,
    )


def _priority(order: int) -> list[str]:
    """Offer low orders first, the base first, translations before rotations."""
    out = [f"E0.{t}.c0" for t in (*TERMS[3:], *TERMS[:3])]
    for k in range(order + 1):
        for i in range(1, 7):
            out += [f"E{i}.{t}.c{k}" for t in (*TERMS[3:], *TERMS[:3])]
    return out


def chebyshev_identifiability(
    setup: ChebyshevSetup, rtol: float = CHEBYSHEV_RTOL, *, check_rank: bool = True
) -> IdentifiabilityReport:
    """Identifiability of the coefficients on these rows, at zero coefficients (module docstring).

    Order-0 (geometric) coefficients lose only exact dependencies (``GEOMETRIC_RTOL``); a
    higher-order one is kept when at least ``rtol`` of its scaled column is outside the span of the
    coefficients kept before it (low orders first, the base first, translations before rotations).
    """
    names = coefficient_names(setup.order)
    _, jac0 = _jacobian(setup, np.zeros(len(names)))
    tol = {name: (GEOMETRIC_RTOL if name.endswith(".c0") else rtol) for name in names}
    return analyze_identifiability(
        jac0, names, priority=_priority(setup.order), rtol=tol, check_rank=check_rank
    )


def fit_chebyshev(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    p_measured_mm: NDArray[np.float64],
    order: int,
    *,
    frame: FrameChoice = "auto",
    range_source: RangeSource = "data",
    range_deg: NDArray[np.float64] | None = None,
    rtol: float = CHEBYSHEV_RTOL,
    max_iter: int = 100,
    check_rank: bool = True,
) -> ChebyshevFit:
    """Fit an order-``order`` Chebyshev error model to measured TCPs (module docstring)."""
    a = as_axes(a_deg)
    n = a.shape[0]
    p_meas = measured_positions(p_measured_mm, n)
    if order < 0:
        raise ValueError(f"Chebyshev order must be >= 0, got {order}")
    params, chosen, _ = registered_start(robot, a, p_meas, frame)
    if range_deg is None:
        range_deg = motion_range_deg(a) if range_source == "data" else robot.axis_limits_deg
    rng = np.asarray(range_deg, dtype=float)
    st = chebyshev_setup(params, a, rng, order)
    report = chebyshev_identifiability(st, rtol, check_rank=check_rank)
    result, coef, active = _identify(st, report.identifiable_index, p_meas, max_iter)
    model = ChebyshevModel(robot, params.world_T_base, order, rng, coef, active)
    rms = float(np.sqrt(np.mean(np.sum(result.residual.reshape(n, 3) ** 2, axis=1))))
    return ChebyshevFit(model=model, frame=chosen, report=report, lm=result, rms_mm=rms, n_rows=n)


def _identify(
    st: ChebyshevSetup,
    idx: NDArray[np.intp],
    p_meas: NDArray[np.float64],
    max_iter: int,
    jacobian_x0: NDArray[np.float64] | None = None,
    fold: bool = False,
) -> tuple[LMResult, NDArray[np.float64], NDArray[np.bool_]]:
    """The coefficients ``idx`` iterated from zero (the others held there): the solver's result,
    every coefficient and which ones were free; a ``fold``'s result lacks the Jacobian at the
    solution, which only a reported fit needs."""
    problem = ChebyshevProblem(st, idx, p_meas)
    result = improved_lm(
        problem.residual,
        problem.jacobian,
        np.zeros(idx.size),
        x_scale="jac",
        max_iter=max_iter,
        jacobian_x0=jacobian_x0,
        jacobian_at_solution=not fold,
    )
    active = np.zeros(problem.n_all, bool)
    active[idx] = True
    return result, problem.full(result.x), active


#: the cross-validation shares, per fold, the setup, the Jacobian at zero and one identifiability
#: analysis per threshold among the orders (:func:`select_order`); False fits every candidate on
#: its own with :func:`fit_chebyshev` (the reference the tests compare with: the same numbers)
SHARED_FOLDS = True


def _fold_sq_errors(
    robot: RobotDescription,
    a: NDArray[np.float64],
    p_meas: NDArray[np.float64],
    test: NDArray[np.bool_],
    orders: Sequence[int],
    rtols: Sequence[float],
    frame: Literal["base", "tracker"],
    range_deg: NDArray[np.float64],
    fitted: Callable[[], None],
) -> NDArray[np.float64]:
    """(orders, rtols) the summed squared held-out errors (mm²) of every candidate fitted on the
    rows outside ``test``; ``fitted()`` is called after each fit.

    The candidates share what does not depend on them: the registration and the setup of the
    highest order (a lower order's basis is the first columns of it), the Jacobian at zero (a
    lower order's columns are some of its columns, the same numbers) and, per threshold, one
    identifiability analysis: the candidates are offered low orders first, so the analysis of
    order m is the first part of that of the highest order, with the same decisions (the
    largest column norm, which the zero test is relative to, is an order-0 one: ``|c_k| ≤ 1``).
    Each candidate's iteration then starts with its columns of that Jacobian.
    """
    train = ~test
    out = np.empty((len(orders), len(rtols)))
    if not SHARED_FOLDS:
        for i, m in enumerate(orders):
            for j, tol in enumerate(rtols):
                fit = fit_chebyshev(
                    robot,
                    a[train],
                    p_meas[train],
                    m,
                    frame=frame,
                    range_deg=range_deg,
                    rtol=tol,
                    check_rank=False,
                )
                out[i, j] = np.sum((fit.model.predict_tcp_mm(a[test]) - p_meas[test]) ** 2)
                fitted()
        return out
    params, _, _ = registered_start(robot, a[train], p_meas[train], frame)
    top_order = max(orders)
    top = chebyshev_setup(params, a[train], range_deg, top_order)
    top_names = coefficient_names(top_order)
    _, jac_top = _jacobian(top, np.zeros(len(top_names)))
    column = {name: i for i, name in enumerate(top_names)}
    for j, tol in enumerate(rtols):
        report = analyze_identifiability(
            jac_top,
            top_names,
            priority=_priority(top_order),
            rtol={name: (GEOMETRIC_RTOL if name.endswith(".c0") else tol) for name in top_names},
            check_rank=False,
            check_condition=False,
            describe_dependent=False,
        )
        kept = set(report.identifiable)
        for i, m in enumerate(orders):
            st = ChebyshevSetup(
                top.links,
                np.ascontiguousarray(top.basis[:, :, : m + 1]),
                top.world_T_base,
                top.tool_xyz_mm,
                m,
            )
            names = coefficient_names(m)
            idx = np.array([k for k, name in enumerate(names) if name in kept], dtype=np.intp)
            cols = np.array([column[names[k]] for k in idx], dtype=np.intp)
            first = jac_top[:, :, cols].reshape(-1, idx.size)
            _, coef, active = _identify(st, idx, p_meas[train], 100, first, fold=True)
            model = ChebyshevModel(robot, params.world_T_base, m, range_deg, coef, active)
            out[i, j] = np.sum((model.predict_tcp_mm(a[test]) - p_meas[test]) ** 2)
            fitted()
    return out


def select_order(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    p_measured_mm: NDArray[np.float64],
    orders: Sequence[int] = CV_ORDERS,
    rtols: Sequence[float] = CV_RTOLS,
    *,
    folds: int = 5,
    seed: int = 0,
    frame: FrameChoice = "auto",
    range_source: RangeSource = "data",
) -> OrderSelection:
    """Choose the order and the removal threshold by ``folds``-fold cross-validation on these rows.

    Every candidate (order, rtol) is fitted on ``folds − 1`` folds and judged on the held-out one;
    the lowest mean held-out 3-D RMS error wins (ties: the lower order, then the larger rtol).
    The joint ranges are those of all the rows given, so every fold maps the angles alike.
    """
    a = as_axes(a_deg)
    p_meas = np.asarray(p_measured_mm, dtype=float)
    n = a.shape[0]
    if folds < 2 or folds > n:
        raise ValueError(f"cross-validation needs 2 <= folds <= rows ({n}), got {folds}")
    if not orders or not rtols:
        raise ValueError("cross-validation needs at least one order and one rtol")
    rng_deg = motion_range_deg(a) if range_source == "data" else robot.axis_limits_deg
    nominal = KinematicParams.from_robot(robot)
    p_nominal = tcp_position_mm(nominal, axes_deg_to_q_rad(a, nominal.sign))
    chosen_frame = detect_frame(p_nominal, p_meas) if frame == "auto" else frame
    fold_of = np.random.default_rng(seed).permutation(n) % folds
    done, total = 0, len(orders) * len(rtols) * folds

    def fitted() -> None:
        nonlocal done
        done += 1
        steps.report("cross-validation fits", done, total)

    sq = np.zeros((len(orders), len(rtols)))
    for f in range(folds):
        rng = np.asarray(rng_deg, dtype=float)
        sq += _fold_sq_errors(robot, a, p_meas, fold_of == f, orders, rtols, chosen_frame, rng, fitted)
    table = [tuple(float(np.sqrt(v / n)) for v in row) for row in sq]
    scores = np.array(table)
    i_order, i_rtol = (int(i) for i in np.unravel_index(int(np.argmin(scores)), scores.shape))
    return OrderSelection(
        tuple(int(m) for m in orders),
        tuple(float(t) for t in rtols),
        tuple(table),
        folds,
        int(orders[i_order]),
        float(rtols[i_rtol]),
    )


def fit_chebyshev_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """The Chebyshev model of seed 000: the spec's order (default 3), or chosen by cross-validation."""
    selection_info: dict[str, Any] | None = None
    rtol = CHEBYSHEV_RTOL
    if spec.order_by_cv:
        sel = select_order(
            robot,
            rows.a_deg,
            rows.xyz_mm,
            folds=min(options.cv_folds, rows.n),
            seed=options.seed,
            frame=options.frame,
        )
        order, rtol = sel.order, sel.rtol
        selection_info = {
            "method": f"{sel.folds}-fold cross-validation on the fit rows (mean held-out 3-D RMS, mm)",
            "orders": list(sel.orders),
            "rtols": list(sel.rtols),
            "cv_rms_mm": [list(r) for r in sel.cv_rms_mm],
            "chosen_order": sel.order,
            "chosen_rtol": sel.rtol,
        }
    else:
        order = DEFAULT_CHEBYSHEV_ORDER if spec.order is None else spec.order
    cf = fit_chebyshev(robot, rows.a_deg, rows.xyz_mm, order, frame=options.frame, rtol=rtol)
    idx = cf.report.identifiable_index  # the columns of the fit's Jacobian, in its order
    names = [cf.model.names[i] for i in idx]
    attach_covariance(cf.model, names, cf.model.coefficients[idx], cf.lm.jacobian, cf.lm.residual)
    info = {
        "kind": spec.kind,
        "rows": rows.n,
        "order": order,
        "rtol": rtol,
        "range_deg": cf.model.range_deg.tolist(),
        "rms_mm": cf.rms_mm,
        "solver": lm_info(cf.lm),
        "identifiability": report_info(cf.report, list_removed=False),
        "order_selection": selection_info,
    }
    return FittedModel(cf.model, cf.frame, info)


def chebyshev_parameters(spec: ModelSpec) -> int:
    """The coefficients of the spec's order (of the smallest candidate order with ``:cv``)."""
    if spec.order_by_cv:
        return n_coefficients(0)
    return n_coefficients(DEFAULT_CHEBYSHEV_ORDER if spec.order is None else spec.order)


KIND = ModelKind(
    "chebyshev",
    "Chebyshev error matrices after every link (seed 000), order 3; chebyshev:m, chebyshev:cv",
    ChebyshevModel,
    fit_chebyshev_kind,
    chebyshev_parameters,
    takes_order=True,
)
