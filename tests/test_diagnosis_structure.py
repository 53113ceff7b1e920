"""The remainder's structure test: out-of-fold share, permutation p-value, Holm over the variables."""

from __future__ import annotations

import numpy as np

from comp_daemon.diagnosis.structure import describe_structure, residual_structure


def _columns(rng: np.random.Generator, n: int) -> dict[str, np.ndarray | None]:
    return {
        "t_s": np.sort(rng.uniform(0.0, 3600.0, n)),
        "a1": rng.uniform(-90.0, 90.0, n),
        "a2": rng.uniform(-60.0, 60.0, n),
        "payload_kg": rng.choice([0.0, 2.0], n),
        "temp_c": None,
        "dir1": rng.choice([-1.0, 1.0], n),
        "a6": np.zeros(n),  # constant: not tested
    }


def test_a_step_in_time_is_found_and_named_in_words() -> None:
    rng = np.random.default_rng(1)
    n = 300
    cols = _columns(rng, n)
    resid = rng.normal(0.0, 0.01, (n, 3))
    resid[cols["t_s"] > 2000.0, 2] += 0.02  # a step in z after 2000 s
    out = {r.against: r for r in residual_structure(resid, cols, np.arange(n), folds=5, seed=0)}
    assert set(out) == {"t_s", "a1", "a2", "payload_kg", "dir1"}
    assert out["t_s"].significant and out["t_s"].share_pct > 20.0
    assert not any(r.significant for name, r in out.items() if name != "t_s")
    words = describe_structure(list(out.values()))
    assert "follows time" in words and "t_s" in words


def test_a_smooth_function_of_an_axis_is_found() -> None:
    rng = np.random.default_rng(2)
    n = 250
    cols = _columns(rng, n)
    resid = rng.normal(0.0, 0.01, (n, 3))
    resid[:, 0] += 0.015 * np.sin(np.deg2rad(2.0 * cols["a2"]))
    out = {r.against: r for r in residual_structure(resid, cols, np.arange(n), folds=5, seed=0)}
    assert out["a2"].significant and not out["t_s"].significant
    assert "A2" in describe_structure(list(out.values()))


def test_pure_noise_rarely_shows_structure() -> None:
    alarms = 0
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        n = 200
        found = residual_structure(
            rng.normal(0.0, 0.01, (n, 3)), _columns(rng, n), np.arange(n), folds=5, seed=seed
        )
        alarms += any(r.significant for r in found)
        assert all(0.0 <= r.share_pct < 10.0 for r in found)
    # family-wise level 1 % per campaign: 20 campaigns give 0 alarms with probability 0.82, ≤ 1 with 0.98
    assert alarms <= 1
