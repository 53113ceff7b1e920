"""The fits' shortcuts change nothing a user sees: on several small campaigns every model keeps and
drops the same parts, with the same held-out gains, chooses the same Chebyshev order and threshold,
and predicts the check rows to 1e-6 mm, with the shortcuts (``fitting.FOLD_SHORTCUTS``, the
identifiability analysis's Gram–Schmidt on a preallocated basis, the base calibration shared by
the kinds built on it, the LM's stop at a converged Jacobian ``lm.PRED_FTOL``, the Chebyshev
cross-validation's shared folds ``chebyshev.SHARED_FOLDS``) and without them (every
cross-validation fold a full fit, the basis grown column by column as before, every kind
calibrating its own base, every LM iteration evaluating its steps, every Chebyshev candidate
fitted on its own)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from comp_daemon.cli import main
from comp_daemon.data.dataset import read_dataset
from comp_daemon.estimation import lm
from comp_daemon.estimation.identifiability import analyze_identifiability
from comp_daemon.models import chebyshev, fitting
from comp_daemon.models.fitting import FitOptions
from comp_daemon.models.registry import fit_spec, parse_model_name
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import load_robot

CAMPAIGNS = {  # name: (scenario, robot, poses, extra sample options)
    "real-like-3-targets": ("real-like", "irb120", 100, ["--targets", "3"]),
    "kr210-cell": ("kr210-cell", "kr210", 120, []),
    "kr210-backlash": ("kr210-backlash", "kr210", 100, []),
}
MODELS = (  # those whose fits select their parts out of fold; a kriging kind after its base's kind
    "kinematic+ratio+backlash+compliance",
    "kriging-backlash+compliance",
    "kinematic+compliance",
    "compliance",
    "chebyshev:cv",
)


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("fast")
    out = {}
    for name, (scenario, _, poses, extra) in CAMPAIGNS.items():
        path = folder / f"{name}.csv"
        argv = ["sim", "sample", "--scenario", scenario, "--n", str(poses), "--seed", "5", "--out", str(path)]
        assert main([*argv, *extra]) == 0
        out[name] = path
    return out


def _reference(m: pytest.MonkeyPatch) -> None:
    """Every shortcut off: full folds, no shared base calibration."""
    m.setattr(fitting, "FOLD_SHORTCUTS", False)
    m.setattr(fitting, "BASE_FITS_KEPT", 0)
    m.setattr(lm, "PRED_FTOL", 0.0)
    m.setattr(chebyshev, "SHARED_FOLDS", False)
    fitting.forget_base_fits()


def _fit_and_check(path: Path, robot_name: str, model: str) -> dict[str, Any]:
    robot = load_robot(robot_name)
    ds = read_dataset(path, limits_deg=robot.axis_limits_deg, min_rows=0, kind="measurement")
    split = ds.split_or_draw()
    rows = MeasuredRows.of_dataset(ds)
    fitted = fit_spec(parse_model_name(model), robot, rows.take(split.fit_rows), FitOptions())
    check = rows.take(split.check_rows)
    pred = fitted.model.predict_tcp_mm(check.a_deg, check.dir, check.payload_kg, check.temp_c)
    err = np.linalg.norm(check.xyz_mm - pred, axis=1)
    return {"info": fitted.info, "check_rms": float(np.sqrt(np.mean(err**2))), "pred": pred}


def _reference_kept(jac: NDArray[np.float64], order: list[int], tol: float) -> list[int]:
    """The Gram–Schmidt of the identifiability analysis as it was: the basis grown by column_stack."""
    norms = np.linalg.norm(jac, axis=0)
    scaled = jac / np.where(norms > 0, norms, 1.0)
    basis = np.zeros((jac.shape[0], 0))
    kept = []
    for pos in order:
        if norms[pos] <= 1e-10 * norms.max():
            continue
        c = scaled[:, pos]
        r = c - basis @ (basis.T @ c)
        r = r - basis @ (basis.T @ r)
        res = float(np.linalg.norm(r))
        if res > tol:
            basis = np.column_stack([basis, r / res])
            kept.append(pos)
    return sorted(kept)


def test_the_identifiable_parameters_are_those_of_the_reference_analysis() -> None:
    rng = np.random.default_rng(3)
    for trial in range(20):
        m, p = 300, 40
        jac = rng.normal(size=(m, p)) * rng.uniform(1e-3, 1e3, size=p)
        # dependent columns: copies, sums and a zero column
        jac[:, 5] = 2.0 * jac[:, 1]
        jac[:, 9] = jac[:, 2] - 0.5 * jac[:, 3]
        jac[:, 17] = 0.0
        if trial % 2:
            jac[:, 30] = jac[:, 31] * 1e-9 + jac[:, 0]  # nearly dependent, within the tolerance
        names = [f"p{i}" for i in range(p)]
        order = list(rng.permutation(p))
        report = analyze_identifiability(jac, names, priority=[names[i] for i in order])
        assert list(report.identifiable_index) == _reference_kept(jac, order, 1e-8)


@pytest.mark.slow
@pytest.mark.parametrize("campaign", list(CAMPAIGNS))
def test_shortcuts_keep_the_selection_and_the_check_errors(
    campaigns: dict[str, Path], campaign: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    robot = CAMPAIGNS[campaign][1]
    for model in MODELS:
        fast = _fit_and_check(campaigns[campaign], robot, model)
        with monkeypatch.context() as m:
            _reference(m)
            ref = _fit_and_check(campaigns[campaign], robot, model)
        sel_fast, sel_ref = fast["info"].get("selection"), ref["info"].get("selection")
        where = f"{campaign}, {model}"
        if sel_ref is None:
            assert sel_fast is None, where
        else:
            assert sel_fast["kept"] == sel_ref["kept"], where
            assert sel_fast["dropped"] == sel_ref["dropped"], where
            for a, b in zip(sel_fast["decisions"], sel_ref["decisions"], strict=True):
                assert a["part"] == b["part"] and a["kept"] == b["kept"], where
                assert a["rms_with_mm"] == pytest.approx(b["rms_with_mm"], abs=1e-6), where
                assert a["rms_without_mm"] == pytest.approx(b["rms_without_mm"], abs=1e-6), where
        order_fast, order_ref = fast["info"].get("order_selection"), ref["info"].get("order_selection")
        if order_ref is not None:
            assert order_fast["chosen_order"] == order_ref["chosen_order"], where
            assert order_fast["chosen_rtol"] == order_ref["chosen_rtol"], where
            np.testing.assert_allclose(order_fast["cv_rms_mm"], order_ref["cv_rms_mm"], rtol=0, atol=1e-6)
        assert abs(fast["check_rms"] - ref["check_rms"]) < 1e-6, where
        assert np.max(np.abs(fast["pred"] - ref["pred"])) < 1e-6, where


@pytest.mark.slow
def test_a_kriging_kind_takes_its_base_calibration_from_the_kinematic_kind(
    campaigns: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``evaluate --models all`` fits ``kinematic+ratio+backlash`` and then ``kriging-backlash`` on
    the same rows: the second calibrates nothing, and is what it is when it calibrates its own base."""
    path, robot = campaigns["kr210-backlash"], CAMPAIGNS["kr210-backlash"][1]
    fitting.forget_base_fits()
    _fit_and_check(path, robot, "kinematic+ratio+backlash")
    calls: list[int] = []
    real = fitting.calibrate_kinematic

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return real(*args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(fitting, "calibrate_kinematic", counted)
        shared = _fit_and_check(path, robot, "kriging-backlash")
    assert calls == []
    with monkeypatch.context() as m:
        _reference(m)
        own = _fit_and_check(path, robot, "kriging-backlash")
    assert shared["info"]["selection"] == own["info"]["selection"]
    assert shared["info"]["base"]["identified"] == own["info"]["base"]["identified"]
    np.testing.assert_array_equal(shared["pred"], own["pred"])
    # the kinds get copies: what one does to its model does not reach the other's
    again = _fit_and_check(path, robot, "kinematic+ratio+backlash")
    assert again["info"] == _fit_and_check(path, robot, "kinematic+ratio+backlash")["info"]
