"""``comp-daemon fit | evaluate | compensate`` end to end on files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, read_dataset, write_dataset
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.artifact import load_model
from comp_daemon.models.compensation import nominal_targets
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")


def _axes(n: int, seed: int) -> np.ndarray:
    lim = KR.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, 90.0)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(0)
    n = 160
    a = _axes(n, 1)
    dirs = rng.choice([-1, 1], size=(n, 6))
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros().with_values(["h2", "h3", "eps2"], [0.005, 0.004, 1e-4])
    p = twin_tcp_mm(KR, truth, eff, a, dirs.astype(float)) + rng.normal(size=(n, 3)) * 0.01
    split = np.where(np.arange(n) < 100, "fit", "check")
    path = tmp_path_factory.mktemp("cli") / "campaign.csv"
    write_dataset(Dataset(a_deg=a, xyz_mm=p, dir=dirs, split=split), path)
    return path


def test_fit_writes_a_loadable_kinematic_model(
    campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "kin.json"
    code = main(
        ["fit", str(campaign), "--robot", "kr210", "--model", "kinematic+ratio+backlash", "--out", str(out)]
    )
    assert code == 0
    assert "parameters identifiable" in capsys.readouterr().out
    loaded = load_model(out, KR)
    assert loaded.model.kind == "kinematic"
    assert loaded.document["data_sha256"] == read_dataset(campaign).content_sha256
    assert loaded.document["fit"]["rows"] == 100
    assert "h2" in loaded.document["fit"]["identified"]


def test_fit_chebyshev_with_a_fixed_order(campaign: Path, tmp_path: Path) -> None:
    out = tmp_path / "cheb.json"
    assert (
        main(
            [
                "fit",
                str(campaign),
                "--robot",
                "kr210",
                "--model",
                "chebyshev",
                "--order",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    loaded = load_model(out)
    assert loaded.model.kind == "chebyshev" and loaded.model.order == 1
    assert loaded.document["fit"]["order_selection"] is None


def test_evaluate_prints_table2_and_writes_json(
    campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "eval.json"
    models = "nominal,kinematic,kinematic+ratio+backlash,chebyshev,chebyshev:cv"
    args = [
        "evaluate",
        str(campaign),
        "--robot",
        "kr210",
        "--models",
        models,
        "--folds",
        "3",
        "--json",
        str(out),
    ]
    code = main(args)
    assert code == 0
    text = capsys.readouterr().out
    assert "kinematic+ratio+backlash" in text and "3D mean" in text
    doc = json.loads(out.read_text())
    assert doc["split"] == {**doc["split"], "fit_rows": 100, "check_rows": 60, "drawn": False}
    table = doc["table2"]
    assert set(table) == {
        "nominal",
        "nominal, base+tool registered",  # the honest baseline beside the raw nominal row
        "kinematic",
        "kinematic+ratio+backlash",
        "chebyshev",
        "chebyshev:cv",
    }
    for stats in table.values():
        assert stats["n"] == 60 and set(stats) >= {"x", "y", "z", "3d"}
    assert table["kinematic"]["3d"]["mean"] < 0.5 * table["nominal"]["3d"]["mean"]
    assert table["kinematic+ratio+backlash"]["3d"]["mean"] < 0.5 * table["kinematic"]["3d"]["mean"]
    # the paper's order by default; cross-validation says what it chose
    assert doc["fits"]["chebyshev"]["order"] == 3 and doc["fits"]["chebyshev"]["order_selection"] is None
    assert doc["fits"]["chebyshev:cv"]["order_selection"]["chosen_order"] in range(5)


def test_compensate_writes_commands_whose_prediction_is_the_target(campaign: Path, tmp_path: Path) -> None:
    model_path = tmp_path / "kin.json"
    assert (
        main(
            ["fit", str(campaign), "--robot", "kr210", "--model", "kinematic+ratio", "--out", str(model_path)]
        )
        == 0
    )
    model = load_model(model_path).model
    a_nominal = _axes(40, 5)
    a_nominal = a_nominal[np.abs(a_nominal[:, 4]) > 10.0][:8]  # away from the wrist singularity
    wanted, _ = nominal_targets(model, a_nominal)
    targets = tmp_path / "targets.csv"
    write_dataset(Dataset(a_deg=None, target_xyz_mm=wanted, pose_id=[f"h{i}" for i in range(8)]), targets)
    out = tmp_path / "corrected.csv"
    assert main(["compensate", str(model_path), str(targets), "--out", str(out), "--robot", "kr210"]) == 0
    corrected = read_dataset(out, kind="targets")
    assert corrected.a_deg is not None and corrected.pose_id == tuple(f"h{i}" for i in range(8))
    reached = model.predict_tcp_mm(corrected.a_deg)
    assert np.linalg.norm(reached - wanted, axis=1).max() < 1e-6
    assert float(max(corrected.extra["predicted_error_mm"], key=float)) < 1e-6

    # nominal programs (a1..a6) are compensated towards their nominal TCP
    program = tmp_path / "program.csv"
    write_dataset(Dataset(a_deg=a_nominal), program)
    out2 = tmp_path / "corrected2.csv"
    assert main(["compensate", str(model_path), str(program), "--out", str(out2)]) == 0
    corrected2 = read_dataset(out2, kind="targets")
    assert corrected2.a_deg is not None
    np.testing.assert_allclose(model.predict_tcp_mm(corrected2.a_deg), wanted, atol=1e-6)


def test_user_errors_exit_2_with_a_message(
    campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "x.json"
    assert main(["fit", str(campaign), "--robot", "kr210", "--model", "spline", "--out", str(out)]) == 2
    assert "unknown model 'spline'" in capsys.readouterr().err
    assert (
        main(["fit", str(campaign), "--robot", "kr210", "--model", "chebyshev+backlash", "--out", str(out)])
        == 2
    )
    assert "models only" in capsys.readouterr().err
    short = tmp_path / "short.csv"
    write_dataset(read_dataset(campaign).subset(np.arange(10)), short)
    assert main(["fit", str(short), "--robot", "kr210", "--model", "kinematic", "--out", str(out)]) == 2
    assert "row" in capsys.readouterr().err
    assert not out.exists()
    broken = tmp_path / "broken.json"
    broken.write_text("{}")
    assert main(["compensate", str(broken), str(campaign), "--out", str(tmp_path / "c.csv")]) == 2
    assert "not a comp-daemon model" in capsys.readouterr().err
