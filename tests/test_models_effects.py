"""The effect model of diagnose.md: definitions, zero == plain FK, Jacobians vs central differences."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from comp_daemon.kinematics.forward import gravity_torques_nm, tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.effects import (
    EFFECTS,
    EffectParams,
    MassModel,
    effect_jacobian,
    effect_param_names,
    joint_output_axes_deg,
    twin_jacobian,
    twin_state,
    twin_tcp_mm,
)
from comp_daemon.models.effects.params import parse_param_name
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("kr210")
PARAMS = KinematicParams.from_robot(ROBOT)
K = 2


def random_axes(rng: np.random.Generator, n: int, robot=ROBOT) -> np.ndarray:
    lim = robot.axis_limits_deg
    lo = np.maximum(lim[:, 0], -150.0) + 5.0
    hi = np.minimum(lim[:, 1], 150.0) - 5.0
    return rng.uniform(lo, hi, size=(n, 6))


def random_effects(rng: np.random.Generator) -> EffectParams:
    return EffectParams(
        backlash_deg=rng.uniform(0.002, 0.02, 6),
        ratio=rng.uniform(-3e-4, 3e-4, 6),
        cyclic_sin_deg=rng.uniform(-0.01, 0.01, (6, K)),
        cyclic_cos_deg=rng.uniform(-0.01, 0.01, (6, K)),
        compliance_rad_per_nm=rng.uniform(1e-8, 5e-7, 6),
        thermal_per_k=1.2e-5,
        t_ref_c=20.0,
    )


def inputs(rng: np.random.Generator, n: int = 7):
    a = random_axes(rng, n)
    d = rng.choice([-1.0, 1.0], size=(n, 6))
    payload = rng.uniform(0.0, 200.0, n)
    temp = rng.uniform(15.0, 32.0, n)
    return a, d, payload, temp


def fk(params, a_deg):
    return tcp_position_mm(params, axes_deg_to_q_rad(a_deg, params.sign))


def test_zero_effects_equal_plain_fk() -> None:
    rng = np.random.default_rng(0)
    a, d, payload, temp = inputs(rng, 20)
    got = twin_tcp_mm(ROBOT, PARAMS, EffectParams.zeros(3), a, d, payload, temp)
    np.testing.assert_allclose(got, fk(PARAMS, a), atol=1e-9)
    assert np.array_equal(twin_tcp_mm(ROBOT, PARAMS, EffectParams(), a), fk(PARAMS, a))


def test_each_effect_is_its_definition() -> None:
    rng = np.random.default_rng(1)
    a, d, payload, temp = inputs(rng, 9)
    eff = random_effects(rng)
    z = EffectParams.zeros(K)
    only = {
        "backlash": replace(z, backlash_deg=eff.backlash_deg),
        "ratio": replace(z, ratio=eff.ratio),
        "cyclic": replace(z, cyclic_sin_deg=eff.cyclic_sin_deg, cyclic_cos_deg=eff.cyclic_cos_deg),
    }
    np.testing.assert_allclose(
        twin_tcp_mm(ROBOT, PARAMS, only["backlash"], a, d), fk(PARAMS, a + eff.backlash_deg * d), atol=1e-9
    )
    np.testing.assert_allclose(
        twin_tcp_mm(ROBOT, PARAMS, only["ratio"], a, d), fk(PARAMS, a * (1 + eff.ratio)), atol=1e-9
    )
    cyc = np.zeros_like(a)
    for k in range(1, K + 1):
        arg = k * np.deg2rad(a)
        cyc += eff.cyclic_sin_deg[:, k - 1] * np.sin(arg) + eff.cyclic_cos_deg[:, k - 1] * np.cos(arg)
    np.testing.assert_allclose(
        twin_tcp_mm(ROBOT, PARAMS, only["cyclic"], a, d), fk(PARAMS, a + cyc), atol=1e-9
    )
    # compliance: theta + C·tau, tau of the commanded configuration with the payload at the TCP
    comp = replace(z, compliance_rad_per_nm=eff.compliance_rad_per_nm)
    q = axes_deg_to_q_rad(a, PARAMS.sign)
    tau = gravity_torques_nm(PARAMS, q, ROBOT.link_mass_kg, ROBOT.link_com_mm, payload)
    expect = tcp_position_mm(PARAMS, q + eff.compliance_rad_per_nm * tau)
    np.testing.assert_allclose(twin_tcp_mm(ROBOT, PARAMS, comp, a, d, payload), expect, atol=1e-9)
    # thermal: a, d scale by 1 + kappa·(T − T_ref), row by row
    therm = replace(z, thermal_per_k=eff.thermal_per_k)
    got = twin_tcp_mm(ROBOT, PARAMS, therm, a, d, payload, temp)
    for r in range(a.shape[0]):
        s = 1.0 + eff.thermal_per_k * (temp[r] - 20.0)
        grown = replace(PARAMS, a_mm=PARAMS.a_mm * s, d_mm=PARAMS.d_mm * s)
        np.testing.assert_allclose(got[r], fk(grown, a[r : r + 1])[0], atol=1e-9)


def test_composition_order_of_all_effects() -> None:
    rng = np.random.default_rng(2)
    a, d, payload, temp = inputs(rng, 5)
    eff = random_effects(rng)
    st = twin_state(ROBOT, PARAMS, eff, a, d, payload, temp)
    k = np.arange(1, K + 1)
    arg = np.deg2rad(a)[:, :, None] * k
    a_eff = (
        a * (1 + eff.ratio)
        + eff.backlash_deg * d
        + (eff.cyclic_sin_deg * np.sin(arg) + eff.cyclic_cos_deg * np.cos(arg)).sum(axis=2)
    )
    np.testing.assert_allclose(st.a_eff_deg, a_eff, atol=1e-12)
    q_cmd = axes_deg_to_q_rad(a, PARAMS.sign)
    tau = gravity_torques_nm(PARAMS, q_cmd, ROBOT.link_mass_kg, ROBOT.link_com_mm, payload)
    np.testing.assert_allclose(st.q_rad, PARAMS.sign * np.deg2rad(a_eff) + eff.compliance_rad_per_nm * tau)


def test_batch_equals_single_pose() -> None:
    rng = np.random.default_rng(3)
    a, d, payload, temp = inputs(rng, 6)
    eff = random_effects(rng)
    batch = twin_tcp_mm(ROBOT, PARAMS, eff, a, d, payload, temp)
    for r in range(6):
        single = twin_tcp_mm(ROBOT, PARAMS, eff, a[r], d[r], payload[r : r + 1], temp[r : r + 1])
        np.testing.assert_allclose(single[0], batch[r], atol=1e-9)


def test_output_angle_reproduces_the_twin() -> None:
    rng = np.random.default_rng(4)
    a, d, payload, _ = inputs(rng, 8)
    eff = random_effects(rng)
    out = joint_output_axes_deg(MassModel.from_robot(ROBOT), PARAMS, eff, a, d, payload)
    np.testing.assert_allclose(fk(PARAMS, out), twin_tcp_mm(ROBOT, PARAMS, eff, a, d, payload), atol=1e-9)


@pytest.mark.parametrize("robot_name", ["kr210", "irb120"])
def test_effect_jacobian_matches_central_differences(robot_name: str) -> None:
    robot = load_robot(robot_name)
    params = KinematicParams.from_robot(robot)
    rng = np.random.default_rng(5)
    a = random_axes(rng, 6, robot)
    d = rng.choice([-1.0, 1.0], size=(6, 6))
    payload = rng.uniform(0.0, 5.0 if robot_name == "irb120" else 200.0, 6)
    temp = rng.uniform(15.0, 32.0, 6)
    eff = random_effects(rng)
    names = eff.names()
    assert names == effect_param_names(EFFECTS, (1, 2, 3, 4, 5, 6), K)
    jac = effect_jacobian(robot, params, eff, names, a, d, payload, temp)
    x0 = eff.get(names)
    for col, name in enumerate(names):
        ref = parse_param_name(name, K)
        h = 0.01 * ref.effect.arrays[ref.array].typical
        e = np.zeros(len(names))
        e[col] = h
        plus = twin_tcp_mm(robot, params, eff.with_values(names, x0 + e), a, d, payload, temp)
        minus = twin_tcp_mm(robot, params, eff.with_values(names, x0 - e), a, d, payload, temp)
        num = (plus - minus) / (2 * h)
        scale = np.abs(num).max() + 1e-3
        np.testing.assert_allclose(jac[:, :, col], num, atol=1e-6 * scale, err_msg=name)


def test_twin_jacobian_geometric_block_matches_central_differences() -> None:
    rng = np.random.default_rng(6)
    a, d, payload, temp = inputs(rng, 5)
    eff = replace(random_effects(rng), compliance_rad_per_nm=np.zeros(6))
    tcp, jac = twin_jacobian(ROBOT, PARAMS, eff, ["h2", "kappa"], a, d, payload, temp)
    assert jac.shape == (5, 3, N_PARAMS + 2)
    np.testing.assert_allclose(tcp, twin_tcp_mm(ROBOT, PARAMS, eff, a, d, payload, temp))
    for col in range(N_PARAMS):
        h = 1e-6
        e = np.zeros(N_PARAMS)
        e[col] = h
        plus = twin_tcp_mm(ROBOT, PARAMS.apply(e), eff, a, d, payload, temp)
        minus = twin_tcp_mm(ROBOT, PARAMS.apply(-e), eff, a, d, payload, temp)
        num = (plus - minus) / (2 * h)
        np.testing.assert_allclose(
            jac[:, :, col], num, atol=1e-5 * (np.abs(num).max() + 1.0), err_msg=str(col)
        )
    np.testing.assert_allclose(
        jac[:, :, N_PARAMS:], effect_jacobian(ROBOT, PARAMS, eff, ["h2", "kappa"], a, d, payload, temp)
    )


def test_geometric_block_with_compliance_leaves_out_only_the_torque_term() -> None:
    rng = np.random.default_rng(7)
    a, d, payload, _ = inputs(rng, 4)
    eff = EffectParams(compliance_rad_per_nm=np.full(6, 2e-7))
    _, jac = twin_jacobian(ROBOT, PARAMS, eff, [], a, d, payload)
    for col in (0, 5, 7, 12):  # theta1, theta2, a2, d3
        h = 1e-6
        e = np.zeros(N_PARAMS)
        e[col] = h
        num = (
            twin_tcp_mm(ROBOT, PARAMS.apply(e), eff, a, d, payload)
            - twin_tcp_mm(ROBOT, PARAMS.apply(-e), eff, a, d, payload)
        ) / (2 * h)
        np.testing.assert_allclose(jac[:, :, col], num, atol=5e-3 * np.abs(num).max())


def test_names_get_and_with_values_round_trip() -> None:
    assert effect_param_names("backlash", (2, 3)) == ["h2", "h3"]
    assert effect_param_names(["cyclic", "thermal"], (1,), 2) == ["c1_1", "c1_2", "s1_1", "s1_2", "kappa"]
    eff = EffectParams.zeros(2)
    names = ["h2", "eps3", "c1_2", "s6_1", "C2", "kappa"]
    values = np.array([0.01, 2e-4, 0.003, -0.004, 3e-7, 1.1e-5])
    set_ = eff.with_values(names, values)
    np.testing.assert_array_equal(set_.get(names), values)
    assert set_.backlash_deg[1] == 0.01 and set_.cyclic_sin_deg[0, 1] == 0.003
    assert set_.cyclic_cos_deg[5, 0] == -0.004 and set_.compliance_rad_per_nm[1] == 3e-7
    np.testing.assert_allclose(set_.add(names, values).get(names), 2 * values)
    assert np.all(eff.get(names) == 0.0)  # frozen original untouched


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: EffectParams(backlash_deg=np.zeros(5)), "backlash_deg"),
        (lambda: EffectParams(cyclic_sin_deg=np.zeros((6, 2))), "cyclic"),
        (lambda: EffectParams(ratio=[0, 0, np.nan, 0, 0, 0]), "ratio"),
        (lambda: EffectParams.zeros(1).get(["c1_2"]), "harmonic 2"),
        (lambda: EffectParams().get(["h7"]), "unknown effect parameter 'h7'"),
        (lambda: effect_param_names("friction"), "unknown effect 'friction'"),
        (
            lambda: twin_tcp_mm(ROBOT, PARAMS, EffectParams(), np.zeros((3, 5))),
            r"a_deg must have shape \(n, 6\), got \(3, 5\)",
        ),
        (
            lambda: twin_tcp_mm(ROBOT, PARAMS, EffectParams(), np.zeros((3, 6)), np.zeros((2, 6))),
            r"dir: expected shape \(3, 6\) like the axis values, got \(2, 6\)",
        ),
        (
            lambda: twin_tcp_mm(ROBOT, PARAMS, EffectParams(), np.zeros((3, 6)), None, np.ones(2)),
            "payload_kg",
        ),
    ],
)
def test_bad_input_is_named(make, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make()


def test_compliance_columns_are_not_zero_where_every_compliance_is_zero() -> None:
    """d tcp / d C_j at C = 0 is J_theta · tau, not 0."""
    from comp_daemon.models.effects import EffectParams, effect_jacobian, twin_tcp_mm
    from comp_daemon.robot.description import load_robot

    robot = load_robot("kr210")
    params = KinematicParams.from_robot(robot)
    a = np.array([[0.0, -90.0, 90.0, 0.0, 30.0, 0.0], [10.0, -60.0, 100.0, 20.0, -30.0, 45.0]])
    zero = EffectParams.zeros()
    jac = effect_jacobian(robot, params, zero, ["C2", "C3"], a, payload_kg=50.0)
    h = 1e-9
    for k, name in enumerate(["C2", "C3"]):
        plus = twin_tcp_mm(robot, params, zero.with_values([name], np.array([h])), a, payload_kg=50.0)
        minus = twin_tcp_mm(robot, params, zero.with_values([name], np.array([-h])), a, payload_kg=50.0)
        num = (plus - minus) / (2 * h)
        assert np.abs(num).max() > 1.0
        np.testing.assert_allclose(jac[:, :, k], num, rtol=1e-5, atol=1e-3)
