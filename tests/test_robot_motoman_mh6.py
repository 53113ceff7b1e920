"""The ``motoman_mh6`` preset: seed 003's MOTOMAN-MH6 as spec B.1 describes it (probe (40, 0, 100) mm,
no mass data), beside the ``mh6`` preset that keeps approximate masses for the gravity models."""

from __future__ import annotations

import numpy as np

from comp_daemon.instruments.crossbar import absorb_probe, crossbar_identifiability, plan_crossbar, seat_probe
from comp_daemon.kinematics.forward import flange_pose
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.robot.description import MASSLESS_PRESETS, PRESETS, load_robot

B1 = {  # spec B.1 (paper Table 2): offset θ0, d, a, α (deg / mm), range
    "offset_deg": (0.0, -90.0, 0.0, 0.0, 0.0, 0.0),
    "d_mm": (0.0, 0.0, 0.0, -638.7, 0.0, -95.0),
    "a_mm": (150.0, 570.0, 130.0, 0.0, 0.0, 0.0),
    "alpha_deg": (-90.0, 180.0, -90.0, 90.0, -90.0, 180.0),
    "min_deg": (-170.0, -180.0, -170.0, -180.0, -135.0, -360.0),
    "max_deg": (170.0, 65.0, 190.0, 180.0, 135.0, 360.0),
}


def test_the_spec_values_the_probe_and_no_masses() -> None:
    robot = load_robot("motoman_mh6")
    assert "motoman_mh6" in PRESETS and MASSLESS_PRESETS <= set(PRESETS)
    for field, values in B1.items():
        assert tuple(getattr(j, field) for j in robot.joints) == values, field
    assert all(j.sign == 1 and j.beta_deg == 0.0 for j in robot.joints)
    np.testing.assert_array_equal(robot.tool_xyz_mm, [40.0, 0.0, 100.0])
    assert not robot.link_mass_kg.any()  # no mass data: the gravity models do not apply
    params = KinematicParams.from_robot(robot)
    zero = flange_pose(params, np.zeros((1, 6)))[0]
    np.testing.assert_allclose(zero[:3, 3], [883.7, 0.0, 700.0], atol=1e-9)  # spec B.1, checked
    np.testing.assert_allclose(zero[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)  # z along +x0
    # the same geometry as the mh6 preset; only the probe (and the masses) differ
    mh6 = load_robot("mh6")
    assert [(j.a_mm, j.d_mm, j.alpha_deg, j.offset_deg) for j in mh6.joints] == [
        (j.a_mm, j.d_mm, j.alpha_deg, j.offset_deg) for j in robot.joints
    ]
    assert mh6.link_mass_kg.any() and robot.sha256 != mh6.sha256


def test_cross_bar_rank_with_the_spec_probe() -> None:
    """Spec acceptance check 12 on the spec's file: 21 of the 24 MDH columns with its off-axis probe
    (absorbed into joint 6), θ1, d1 and α6 unseen; with the probe fitted too, θ1 and d1."""
    robot = load_robot("motoman_mh6")
    params = KinematicParams.from_robot(robot)
    plan = plan_crossbar(30, np.random.default_rng(0), bar_l_mm=400.0)
    a_deg, ok = seat_probe(params, robot.sign, robot.axis_limits_deg, plan)
    a_deg = a_deg[ok][:18]
    assert len(a_deg) == 18
    lengths = np.full(18, 400.0)
    off = crossbar_identifiability(absorb_probe(params), a_deg, robot.sign, lengths)
    assert off.rank_svd == off.n_identifiable == 21
    assert set(off.removed_names("zero")) == {"theta1", "d1", "alpha6"}
    product = crossbar_identifiability(params, a_deg, robot.sign, lengths, tool=True)
    assert product.rank_svd == 21 and set(product.removed_names("zero")) == {"theta1", "d1"}
