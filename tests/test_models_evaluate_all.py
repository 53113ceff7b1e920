"""``evaluate --models all`` and the approach directions inferred from the pose order, through the doors."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import read_dataset, write_dataset
from comp_daemon.models.artifact import load_model
from comp_daemon.models.registry import ALL_MODELS
from comp_daemon.preparation.options import FitSettings
from comp_daemon.robot.description import load_robot
from comp_daemon.service.job_kinds import run_fit

KR = load_robot("kr210")
SCENARIOS = Path(__file__).resolve().parents[1] / "comp_daemon" / "sim" / "scenarios"


@pytest.fixture(scope="module")
def backlash_no_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated backlash-only campaign (kr210-backlash, 160 poses in visiting order), dir dropped."""
    folder = tmp_path_factory.mktemp("nodir")
    full = folder / "full.csv"
    scenario = str(SCENARIOS / "kr210-backlash.toml")
    assert main(["sim", "sample", "--scenario", scenario, "--n", "160", "--out", str(full)]) == 0
    ds = read_dataset(full)
    assert ds.dir is not None
    path = folder / "nodir.csv"
    write_dataset(dataclasses.replace(ds, dir=None), path)
    return path


def _evaluate(data: Path, models: str, out: Path, *extra: str) -> dict:
    code = main(["evaluate", str(data), "--robot", "kr210", "--models", models, "--json", str(out), *extra])
    assert code == 0
    return json.loads(out.read_text())


def _rms(doc: dict, model: str) -> float:
    return float(doc["table2"][model]["3d"]["rms"])


def test_inferred_directions_beat_the_same_models_without(
    backlash_no_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with_dir = _evaluate(backlash_no_dir, "kinematic+ratio+backlash,kriging-backlash", tmp_path / "a.json")
    out = capsys.readouterr().out
    assert "inferred from the sign of each axis' last motion" in out
    assert "inferred" in with_dir["directions"]
    # without dir the backlash models are refused; what is left is the same models without backlash
    assert (
        main(
            [
                "evaluate",
                str(backlash_no_dir),
                "--robot",
                "kr210",
                "--models",
                "kriging-backlash",
                "--no-infer-dir",
            ]
        )
        == 2
    )
    assert "dir1..dir6" in capsys.readouterr().err
    without = _evaluate(backlash_no_dir, "kinematic+ratio,kriging", tmp_path / "b.json", "--no-infer-dir")
    assert without["directions"] is None
    assert _rms(with_dir, "kinematic+ratio+backlash") < 0.5 * _rms(without, "kinematic+ratio")
    assert _rms(with_dir, "kriging-backlash") < 0.5 * _rms(without, "kriging")


def test_fit_says_it_inferred_and_the_artifact_keeps_the_file_hash(
    backlash_no_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "m.json"
    argv = ["fit", str(backlash_no_dir), "--robot", "kr210", "--model", "kinematic+ratio+backlash"]
    assert main([*argv, "--out", str(out)]) == 0
    assert "approach directions (dir1..dir6) inferred" in capsys.readouterr().out
    doc = load_model(out, KR).document
    assert "inferred" in doc["fit"]["directions"]
    assert doc["data_sha256"] == read_dataset(backlash_no_dir).content_sha256
    assert main([*argv, "--out", str(tmp_path / "n.json"), "--no-infer-dir"]) == 2
    assert "needs the dir1..dir6 column(s)" in capsys.readouterr().err


def test_fit_job_infers_directions_unless_told_not_to(backlash_no_dir: Path) -> None:
    csv = backlash_no_dir.read_text()
    done = run_fit(csv, "kr210", "kinematic+ratio+backlash", None, 1, progress=lambda *a, **k: None)
    stats = done["stats"]
    assert "inferred" in stats["directions"]
    assert stats["table2"]["model"]["3d"]["rms"] < 0.1
    with pytest.raises(ValueError, match=r"dir1\.\.dir6"):
        run_fit(
            csv,
            "kr210",
            "kinematic+ratio+backlash",
            None,
            1,
            FitSettings(infer_dir=False),
            progress=lambda *a, **k: None,
        )
    plain = run_fit(csv, "kr210", "kinematic", None, 1, progress=lambda *a, **k: None)
    assert plain["stats"]["directions"] is None  # the model does not use them: nothing inferred


def test_evaluate_all_ranks_every_model_with_times(
    backlash_no_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = _evaluate(backlash_no_dir, "all", tmp_path / "all.json")
    captured = capsys.readouterr()
    assert list(doc["table2"]) == doc["ranking"]
    # every model, and beside the raw nominal row the nominal robot with base and tool registered
    assert sorted(doc["ranking"]) == sorted([*ALL_MODELS, "nominal, base+tool registered"])
    rms = [_rms(doc, m) for m in doc["ranking"]]
    assert rms == sorted(rms)
    for name in ALL_MODELS:
        assert doc["timing"][name]["fit_s"] >= 0.0 and doc["timing"][name]["predict_s"] > 0.0
        assert name in captured.out
    assert "check RMS" not in captured.err  # progress and per-model lines only on a terminal
    assert "fit s" in captured.out and "pred ms" in captured.out
    # the backlash family wins on a backlash campaign, nothing chosen is worse than kinematic
    assert doc["ranking"][0] in (
        "kinematic+ratio+backlash",
        "kriging-backlash",
        "kriging-backlash+compliance",
        "kinematic+ratio+backlash+compliance",
    )
    assert _rms(doc, doc["ranking"][0]) < 0.5 * _rms(doc, "kinematic")
    no_dir = _evaluate(backlash_no_dir, "all", tmp_path / "nd.json", "--no-infer-dir")
    assert set(no_dir["skipped"]) == {m for m in ALL_MODELS if "backlash" in m}
    assert "left out (no dir columns)" in capsys.readouterr().err
