"""Identifiability (seed 003): zero and dependent columns of the identification Jacobian, by name."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from comp_daemon.estimation.identifiability import (
    analyze_identifiability,
    mdh_priority,
    offer_order,
    parallel_joints,
    select_columns,
)
from comp_daemon.kinematics.forward import identification_jacobian, tcp_position_mm
from comp_daemon.kinematics.params import PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import RobotDescription, load_robot

SEED003_IDENTIFIABLE = (
    # seed 003, §4.1: Δx = [Δθ2…Δθ6, Δβ2, Δd3…Δd6, Δa1…Δa6, Δα1…Δα5], 21 parameters
    *(f"theta{j}" for j in range(2, 7)),
    "beta2",
    *(f"d{j}" for j in range(3, 7)),
    *(f"a{j}" for j in range(1, 7)),
    *(f"alpha{j}" for j in range(1, 6)),
)


def _random_q(robot: RobotDescription, n: int, seed: int) -> np.ndarray:
    lim = robot.axis_limits_deg
    a = np.random.default_rng(seed).uniform(lim[:, 0], lim[:, 1], size=(n, 6))
    return axes_deg_to_q_rad(a, robot.sign)


def _mh6_probe_as_frame6() -> KinematicParams:
    """MH6 with seed 003's probe: the tool point is the origin of frame 6 (a6 != 0, tool offset zero)."""
    p = KinematicParams.from_robot(load_robot("mh6"))
    # tool (40, 0, 120) after Rx(alpha6 = 180°) is (40, 0, -120) in the frame before it: a6 += 40, d6 -= 120
    folded = replace(
        p,
        a_mm=np.array([*p.a_mm[:5], p.a_mm[5] + 40.0]),
        d_mm=np.array([*p.d_mm[:5], p.d_mm[5] - 120.0]),
        tool_xyz_mm=np.zeros(3),
    )
    q = _random_q(load_robot("mh6"), 10, 0)
    np.testing.assert_allclose(tcp_position_mm(folded, q), tcp_position_mm(p, q), atol=1e-9)
    return folded


def _crossbar_rows(params: KinematicParams, q: np.ndarray) -> np.ndarray:
    """Seed 003 eqs 9 and 11: distance |AC|, |BD| and perpendicularity AC ⊥ BD rows of the cross bar."""
    p = tcp_position_mm(params, q)
    jac = identification_jacobian(params, q)
    pa, pb, pc, pd = p[0::4], p[1::4], p[2::4], p[3::4]
    ja, jb, jc, jd = jac[0::4], jac[1::4], jac[2::4], jac[3::4]

    def distance(p1, p2, j1, j2):  # type: ignore[no-untyped-def]
        u = (p1 - p2) / np.linalg.norm(p1 - p2, axis=1)[:, None]
        return np.einsum("ni,nij->nj", u, j1 - j2)

    perpendicular = np.einsum("ni,nij->nj", pc - pa, jd - jb) + np.einsum("ni,nij->nj", pd - pb, jc - ja)
    return np.concatenate([distance(pa, pc, ja, jc), distance(pb, pd, jb, jd), perpendicular])


def test_mh6_cross_bar_reproduces_seed003_21_parameters() -> None:
    params = _mh6_probe_as_frame6()
    rows = _crossbar_rows(params, _random_q(load_robot("mh6"), 4 * 18, 1))  # 18 placements, as the paper
    # seed 003's candidates: theta, d, a, alpha of every joint, beta2 in place of d2 (joints 2, 3 parallel)
    candidates = [f"{k}{j}" for j in range(1, 7) for k in ("theta", "d", "a", "alpha")]
    candidates[candidates.index("d2")] = "beta2"
    report = analyze_identifiability(rows, PARAM_NAMES, candidates=candidates, priority=mdh_priority(params))
    assert sorted(report.identifiable) == sorted(SEED003_IDENTIFIABLE)
    assert report.n_identifiable == 21
    assert report.removed_names("zero") == ("theta1", "d1", "alpha6")
    assert report.rank_qr == report.rank_svd == 21


def test_mh6_absolute_positions_with_base_frame_name_theta1_and_d1_as_base_terms() -> None:
    params = _mh6_probe_as_frame6()
    jac = identification_jacobian(params, _random_q(load_robot("mh6"), 60, 2))
    candidates = [f"{k}{j}" for j in range(1, 7) for k in ("theta", "d", "a", "alpha")]
    candidates[candidates.index("d2")] = "beta2"
    candidates += [n for n in PARAM_NAMES if n.startswith("base_")]
    report = analyze_identifiability(jac, PARAM_NAMES, candidates=candidates, priority=mdh_priority(params))
    assert report.n_identifiable == 27  # seed 003's 21 and the six of the base frame
    removed = {r.name: r for r in report.removed}
    assert set(removed) == {"theta1", "d1", "alpha6"}
    assert removed["alpha6"].reason == "zero"
    assert removed["theta1"].depends_on == ("base_rz",)
    assert removed["theta1"].coefficients[0] == pytest.approx(1.0)
    assert removed["d1"].depends_on == ("base_z",)


KR210_REMOVED = {
    "theta1",
    "d1",
    "beta1",
    "d2",
    "beta3",
    "beta4",
    "beta5",
    "theta6",
    "d6",
    "a6",
    "alpha6",
    "beta6",
}


def test_kr210_with_base_and_tool_keeps_27_and_names_the_rest() -> None:
    kr = load_robot("kr210")
    params = KinematicParams.from_robot(kr)
    assert parallel_joints(params) == (False, True, False, False, False, False)
    jac = identification_jacobian(params, _random_q(kr, 100, 3))
    report = analyze_identifiability(jac, PARAM_NAMES, priority=mdh_priority(params))
    assert report.n_identifiable == 27  # 4R + 3 of a position-only calibration: 4·6 + 3
    assert report.rank_qr == report.rank_svd == 27
    assert set(report.removed_names()) == KR210_REMOVED
    assert report.removed_names("zero") == ()
    removed = {r.name: r for r in report.removed}
    # parallel joints 2, 3: beta2 is kept and d2 moves the TCP exactly like d3
    assert "beta2" in report.identifiable
    assert removed["d2"].depends_on == ("d3",)
    assert removed["d2"].coefficients[0] == pytest.approx(1.0)
    # joint 6's parameters only move the TCP point like the tool offset does
    for name in ("theta6", "d6", "a6", "alpha6", "beta6"):
        assert set(removed[name].depends_on) <= {"tool_x", "tool_y", "tool_z"}
    assert removed["a6"].depends_on == ("tool_x",)


def test_dependency_coefficients_are_reported_exactly() -> None:
    rng = np.random.default_rng(7)
    a, b, c = rng.normal(size=(3, 30))
    jac = np.stack([a, np.zeros(30), b, 2.0 * a - 3.0 * b, c], axis=1)
    report = analyze_identifiability(jac, ["a", "z", "b", "dep", "c"])
    assert report.identifiable == ("a", "b", "c")
    zero, dep = report.removed
    assert (zero.name, zero.reason) == ("z", "zero")
    assert (dep.name, dep.reason) == ("dep", "dependent")
    assert dict(zip(dep.depends_on, dep.coefficients, strict=True)) == pytest.approx({"a": 2.0, "b": -3.0})
    assert "dep: dependent" in report.summary()


def test_priority_decides_which_of_a_dependent_pair_is_kept() -> None:
    rng = np.random.default_rng(8)
    a = rng.normal(size=20)
    jac = np.stack([a, 5.0 * a], axis=1)
    first = analyze_identifiability(jac, ["p", "q"])
    second = analyze_identifiability(jac, ["p", "q"], priority=["q", "p"])
    assert first.identifiable == ("p",)
    assert second.identifiable == ("q",)
    assert second.removed[0].coefficients[0] == pytest.approx(0.2)


def test_bad_input_is_refused_by_name() -> None:
    jac = np.ones((6, 2))
    with pytest.raises(ValueError, match="3 names for a Jacobian with 2 columns"):
        analyze_identifiability(jac, ["a", "b", "c"])
    with pytest.raises(ValueError, match="unknown parameter name"):
        analyze_identifiability(jac, ["a", "b"], candidates=["a", "x"])
    with pytest.raises(ValueError, match="no tolerance for: b"):
        analyze_identifiability(jac, ["a", "b"], rtol={"a": 1e-8})


def test_offer_order_puts_the_priority_first_and_skips_what_is_not_a_candidate() -> None:
    index = {name: i for i, name in enumerate(["a", "b", "c", "d"])}
    assert offer_order(index, None, None) == ["a", "b", "c", "d"]
    assert offer_order(index, ["d", "b", "a"], None) == ["d", "b", "a"]
    # "c" is a column but not a candidate: the priority's mention of it is skipped
    assert offer_order(index, ["a", "b", "d"], ["c", "d", "b"]) == ["d", "b", "a"]
    with pytest.raises(ValueError, match="in priority: x"):
        offer_order(index, None, ["x", "a"])


def test_select_columns_keeps_a_column_only_when_its_new_part_exceeds_its_tolerance() -> None:
    e1, e2, e3 = np.eye(3)
    tilted = (e1 + 0.01 * e2) / np.linalg.norm(e1 + 0.01 * e2)  # new part 0.01/|.| beside e1
    scaled = np.stack([e1, np.zeros(3), tilted, tilted, e3], axis=1)
    is_zero = np.array([False, True, False, False, False])
    new_part = 0.01 / np.linalg.norm(e1 + 0.01 * e2)
    # the first tilted column's tolerance is just above its new part, the second's just below
    tol = np.array([1e-8, 1e-8, new_part * 1.001, new_part * 0.999, 1e-8])
    kept, kept_res, status = select_columns(scaled, is_zero, tol)
    assert kept == [0, 3, 4]
    assert kept_res == pytest.approx([1.0, new_part, 1.0])
    assert status[1] == ("zero", 0.0)
    assert status[2][0] == "dependent"
    assert status[2][1] == pytest.approx(new_part)
