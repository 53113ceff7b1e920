"""Every entry of the effect catalogue is complete and consistent: a new entry is checked unedited.

Walks :data:`EFFECT_CATALOGUE`: parameters with units and layouts, unique names, the data columns
and the words when they are missing, the Jacobian of every parameter against central differences
of the twin, a diagnosis candidate, fitted-value JSON keys, a report driver and advice.
"""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

import comp_daemon.models.effects.catalogue as catalogue_module
from comp_daemon.diagnosis.candidates import all_candidates, effect_params_json
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models.effects import (
    EFFECT_CATALOGUE,
    EFFECTS,
    Effect,
    EffectData,
    EffectParams,
    MassModel,
    effect_by_name,
    effect_jacobian,
    effect_param_names,
    twin_inputs,
    twin_state,
    twin_tcp_mm,
)
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("kr210")
PARAMS = KinematicParams.from_robot(ROBOT)
K = 2
#: the per-pose data columns the twin and the diagnosis know
DATA_COLUMNS = {"dir", "payload_kg", "temp_c", "clock"}
IDS = [e.name for e in EFFECT_CATALOGUE]


def _poses(rng: np.random.Generator, n: int = 9):
    lim = ROBOT.axis_limits_deg
    lo = np.maximum(lim[:, 0], -150.0) + 5.0
    hi = np.minimum(lim[:, 1], 150.0) - 5.0
    a = rng.uniform(lo, hi, size=(n, 6))
    d = rng.choice([-1.0, 1.0], size=(n, 6))
    return a, d, rng.uniform(0.0, 200.0, n), rng.uniform(15.0, 32.0, n)


def _clock(a: np.ndarray) -> np.ndarray:
    """A campaign clock (h) over the poses; the step of :func:`_random` acts on its second half."""
    return np.linspace(0.0, 8.0, len(a))


STEP_AT_H = 4.0


def _random(rng: np.random.Generator) -> EffectParams:
    """Every parameter of every catalogue entry non-zero."""
    arrays = {}
    for e in EFFECT_CATALOGUE:
        for arr in e.arrays:
            shape = {"joint": (6,), "harmonic": (6, K), "scalar": ()}[arr.layout]
            value = arr.typical * rng.uniform(0.5, 1.5, shape) * rng.choice([-1.0, 1.0], shape)
            arrays[arr.attr] = float(value) if arr.layout == "scalar" else value
    return EffectParams(step_at=STEP_AT_H, **arrays)


def effect_param_names_of(arr, n_harmonics: int) -> list[str]:
    """Every parameter name of one array."""
    return [n for j in (1, 2, 3, 4, 5, 6) for n in arr.names(j, n_harmonics)]


def test_names_are_unique_and_the_vocabulary_is_the_catalogue() -> None:
    assert EFFECTS == tuple(IDS)
    assert len(set(IDS)) == len(IDS)
    attrs = [arr.attr for e in EFFECT_CATALOGUE for arr in e.arrays]
    symbols = [arr.symbol for e in EFFECT_CATALOGUE for arr in e.arrays]
    keys = [arr.json_key for e in EFFECT_CATALOGUE for arr in e.arrays]
    assert len(set(attrs)) == len(attrs) and len(set(symbols)) == len(symbols) and len(set(keys)) == len(keys)
    all_names = effect_param_names(EFFECTS, (1, 2, 3, 4, 5, 6), K)
    assert len(set(all_names)) == len(all_names)


@pytest.mark.parametrize("effect", EFFECT_CATALOGUE, ids=IDS)
def test_entry_declares_units_columns_and_words(effect: Effect) -> None:
    assert effect.meaning and effect.formula
    for arr in effect.arrays:
        assert arr.unit and arr.meaning and arr.json_key
        assert arr.layout in ("joint", "harmonic", "scalar")
        assert re.fullmatch(r"[A-Za-z]+", arr.symbol)
        assert arr.typical > 0
    assert set(effect.columns) <= DATA_COLUMNS
    assert set(effect.required) <= set(effect.columns)
    assert all(words.strip() for words in effect.required.values())
    assert "{axes}" in effect.action or not effect.per_joint
    assert effect.action.format(axes="A2 and A3")
    assert effect_by_name(effect.name) is effect


def test_catalogue_docstring_table_lists_every_parameter_with_its_unit() -> None:
    doc = catalogue_module.__doc__ or ""
    for e in EFFECT_CATALOGUE:
        for arr in e.arrays:
            stem = {
                "joint": f"{arr.symbol}{{i}}",
                "harmonic": f"{arr.symbol}{{i}}_{{k}}",
                "scalar": arr.symbol,
            }
            row = next((line for line in doc.splitlines() if f"``{stem[arr.layout]}``" in line), None)
            assert row is not None, f"{arr.symbol} missing from the table of the catalogue's docstring"
            assert arr.unit in row


@pytest.mark.parametrize("effect", EFFECT_CATALOGUE, ids=IDS)
def test_jacobian_agrees_with_central_differences_of_the_twin(effect: Effect) -> None:
    rng = np.random.default_rng(sum(map(ord, effect.name)))
    a, d, payload, temp = _poses(rng)
    eff = _random(rng)
    names = effect.names([1, 2, 3, 4, 5, 6], K)
    jac = effect_jacobian(ROBOT, PARAMS, eff, names, a, d, payload, temp, clock=_clock(a))
    values = eff.get(names)
    moving = 0
    for col, name in enumerate(names):
        h = 0.1 * next(arr.typical for arr in effect.arrays if name in effect_param_names_of(arr, K))
        plus = twin_tcp_mm(
            ROBOT, PARAMS, eff.with_values([name], [values[col] + h]), a, d, payload, temp, clock=_clock(a)
        )
        minus = twin_tcp_mm(
            ROBOT, PARAMS, eff.with_values([name], [values[col] - h]), a, d, payload, temp, clock=_clock(a)
        )
        num = (plus - minus) / (2 * h)
        scale = np.abs(num).max()
        moving += bool(scale > 0)  # C1 of a robot with a vertical A1 carries no gravity torque
        np.testing.assert_allclose(jac[:, :, col], num, rtol=1e-5, atol=1e-6 * scale + 1e-12)
    assert moving >= len(names) - 1


@pytest.mark.parametrize("effect", EFFECT_CATALOGUE, ids=IDS)
def test_zero_entry_is_no_effect_and_each_entry_acts_alone(effect: Effect) -> None:
    rng = np.random.default_rng(7)
    a, d, payload, temp = _poses(rng)
    zero = EffectParams.zeros(K, step_at=STEP_AT_H)
    base = twin_tcp_mm(ROBOT, PARAMS, zero, a, d, payload, temp, clock=_clock(a))
    names = effect.names([1, 2, 3, 4, 5, 6], K)
    alone = zero.with_values(names, _random(rng).get(names))
    assert not alone.is_zero(effect)
    assert all(alone.is_zero(other) for other in EFFECT_CATALOGUE if other is not effect)
    moved = twin_tcp_mm(ROBOT, PARAMS, alone, a, d, payload, temp, clock=_clock(a))
    assert np.abs(moved - base).max() > 1e-3


@pytest.mark.parametrize("effect", EFFECT_CATALOGUE, ids=IDS)
def test_entry_has_diagnosis_candidates_json_and_a_driver(effect: Effect) -> None:
    cands = [c for c in all_candidates(K) if c.effect == effect.name]
    if effect.per_joint:
        assert [c.joint for c in cands] == [1, 2, 3, 4, 5, 6]
        assert all(c.names == tuple(effect.names([c.joint], K)) for c in cands if c.joint)
    else:
        assert len(cands) == 1 and cands[0].joint is None
    rng = np.random.default_rng(11)
    eff = _random(rng)
    joints = [2, 3] if effect.per_joint else []
    doc = effect_params_json(effect.name, joints, eff)
    for arr in effect.arrays:
        assert arr.json_key in doc
    for setting in effect.settings:
        assert doc[setting] == getattr(eff, setting)
    a, d, payload, temp = _poses(rng)
    inputs = twin_inputs(MassModel.from_robot(ROBOT), PARAMS, a, d, payload, temp, clock=_clock(a))
    x, label = effect.driver(inputs, joints[0] if joints else None)
    assert x.shape == (a.shape[0],) and np.all(np.isfinite(x)) and label


def test_a_time_like_driver_without_its_column_is_the_row_number() -> None:
    a, d, payload, _ = _poses(np.random.default_rng(12))
    inputs = twin_inputs(MassModel.from_robot(ROBOT), PARAMS, a, d, payload, None, clock=None)
    for effect in EFFECT_CATALOGUE:
        if {"temp_c", "clock"} & set(effect.columns):
            x, label = effect.driver(inputs, None)
            assert label == "row" and np.array_equal(x, np.arange(a.shape[0], dtype=float)), effect.name


@pytest.mark.parametrize("effect", EFFECT_CATALOGUE, ids=IDS)
def test_data_check_names_missing_and_constant_columns(effect: Effect) -> None:
    rng = np.random.default_rng(13)
    a, d, payload, temp = _poses(rng)
    st = twin_state(ROBOT, PARAMS, EffectParams.zeros(K), a, d, payload, temp, with_torques=True)
    rows = MeasuredRows(a, np.zeros((len(a), 3)), d, payload, temp, clock=_clock(a))
    full = EffectData(rows, st.tau_nm, np.ones(6, dtype=bool))
    joint = 2 if effect.per_joint else None
    assert effect.unfit_reason(full, joint) is None
    for column, words in effect.required.items():
        assert effect.unfit_reason(replace(full, rows=replace(rows, **{column: None})), joint) == words
    if effect.per_joint:
        still = replace(full, moves_tcp=np.array([True, False, True, True, True, True]))
        assert "does not move the TCP" in (effect.unfit_reason(still, 2) or "")
    # every pose the same, at one temperature and load: nothing an effect can be identified from
    frozen = EffectData(
        replace(rows.take(np.zeros(len(a), dtype=np.int64)), clock=np.zeros(len(a))),
        np.repeat(st.tau_nm[:1], len(a), axis=0),
        np.ones(6, dtype=bool),
    )
    assert effect.unfit_reason(frozen, joint)
