"""The HTTP fit and diagnosis jobs take the options of ``comp-daemon fit`` and ``diagnose``: the same
artifact from the same file and options on both doors, a bad value refused in the same sentence
(the HTTP answer names the field), the options recorded with the job."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from diagnosis_campaigns import make_campaign
from service_client import in_process_service, job_done
from test_service_api import auth, make_settings

from comp_daemon.cli import build_parser, main
from comp_daemon.data.dataset import write_dataset
from comp_daemon.diagnosis import DiagnoseOptions
from comp_daemon.diagnosis.options import diagnose_options
from comp_daemon.preparation.options import COMPARED_MODELS, DiagnosisSettings, FitSettings
from comp_daemon.service.schemas import DiagnosisIn, FitIn


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[httpx.AsyncClient]:
    settings = make_settings(tmp_path, jobs={"workers": 1}, robot={"name": "irb120"})
    async with in_process_service(settings) as (c, _):
        yield c


async def _upload(client: httpx.AsyncClient, path: Path) -> int:
    up = await client.post(
        f"/api/datasets?name={path.stem}",
        content=path.read_text(),
        headers={**auth("engineer"), "Content-Type": "text/csv"},
    )
    assert up.status_code == 201, up.text
    return int(up.json()["id"])


async def _fit_job(client: httpx.AsyncClient, body: dict[str, Any]) -> dict[str, Any]:
    r = await client.post("/api/fits", json=body, headers=auth("engineer"))
    assert r.status_code == 202, r.text
    done = await job_done(client, r.json()["id"], limit_s=180.0)
    assert done["state"] == "done", done["error"]
    return done


async def _artifact(client: httpx.AsyncClient, job_id: int) -> dict[str, Any]:
    models = (await client.get("/api/models", headers=auth("viewer"))).json()
    model_id = next(m["id"] for m in models if m["job_id"] == job_id)
    r = await client.get(f"/api/models/{model_id}/artifact", headers=auth("viewer"))
    assert r.status_code == 200
    return dict(r.json())


def _cli_fit(data: Path, out: Path, robot: str, model: str, *flags: str) -> dict[str, Any]:
    assert main(["fit", str(data), "--robot", robot, "--model", model, *flags, "--out", str(out)]) == 0
    return dict(json.loads(out.read_text()))


@pytest.mark.parametrize(
    ("option", "flag"), [("ridge", "--ridge"), ("fix_near_dependent", "--fix-near-dependent")]
)
async def test_a_ballbar_fit_job_takes_the_ridge_and_the_fix_as_the_command_line_does(
    client: httpx.AsyncClient, tmp_path: Path, option: str, flag: str
) -> None:
    data = tmp_path / "bb.csv"
    sample = ["sim", "sample", "--scenario", "ballbar", "--n", "3", "--seed", "1", "--out", str(data)]
    assert main(sample) == 0
    plain = _cli_fit(data, tmp_path / "plain.json", "irb120", "poe")
    cli = _cli_fit(data, tmp_path / "cli.json", "irb120", "poe", flag)
    dataset_id = await _upload(client, data)
    done = await _fit_job(client, {"dataset_id": dataset_id, "model": "poe", option: True})
    assert done["params"][option] is True
    http = await _artifact(client, done["id"])
    assert http["model"] == cli["model"] and http["data_sha256"] == cli["data_sha256"]
    assert http["model"] != plain["model"]  # the option changed the fit
    for key in ("ridge", "near_dependent_fixed", "identified"):
        assert http["fit"][key] == cli["fit"][key]
    assert done["result"]["stats"]["near_dependent_fixed"] == cli["fit"]["near_dependent_fixed"]


async def test_a_probe_fit_job_weighs_the_orientation_as_the_command_line_does(
    client: httpx.AsyncClient, tmp_path: Path
) -> None:
    data = tmp_path / "probe.csv"
    sample = ["sim", "sample", "--scenario", "irb120-geometric", "--n", "80", "--seed", "3"]
    assert main([*sample, "--tracker-frame", "--probe-sigma-deg", "0.05", "--out", str(data)]) == 0
    plain = _cli_fit(data, tmp_path / "plain.json", "irb120", "kinematic")
    cli = _cli_fit(data, tmp_path / "cli.json", "irb120", "kinematic", "--probe-sigma-deg", "0.5")
    assert cli["fit"]["probe_sigma_deg"] == 0.5 and plain["fit"]["probe_sigma_deg"] == 0.01
    dataset_id = await _upload(client, data)
    done = await _fit_job(client, {"dataset_id": dataset_id, "model": "kinematic", "probe_sigma_deg": 0.5})
    assert done["params"]["probe_sigma_deg"] == 0.5
    http = await _artifact(client, done["id"])
    assert http["model"] == cli["model"] and http["fit"]["probe_sigma_deg"] == 0.5
    assert http["model"] != plain["model"]


@pytest.mark.parametrize(
    ("path", "field", "value", "flag"),
    [
        ("/api/fits", "probe_sigma_deg", -1, "--probe-sigma-deg"),
        ("/api/fits", "folds", 21, "--folds"),
        ("/api/fits", "frame", "robot", "--frame"),
        ("/api/diagnoses", "harmonics", 9, "--harmonics"),
        ("/api/diagnoses", "alpha", 0.7, "--alpha"),
        ("/api/diagnoses", "tracker_sigma_mm", 0, "--tracker-sigma-mm"),
        ("/api/diagnoses", "effects", ["friction"], "--effects"),
        ("/api/diagnoses", "compare_models", "kinematic,splines", "--compare-models"),
    ],
)
async def test_a_bad_option_is_refused_naming_the_field_in_the_command_lines_words(
    client: httpx.AsyncClient,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    path: str,
    field: str,
    value: Any,
    flag: str,
) -> None:
    body = {"dataset_id": 1, field: value, **({"model": "kinematic"} if path == "/api/fits" else {})}
    r = await client.post(path, json=body, headers=auth("engineer"))
    assert r.status_code == 422, r.text
    message = r.json()["message"]
    assert message.startswith(f"body.{field}: ")
    assert r.json()["column"] == field
    command = "fit" if path == "/api/fits" else "diagnose"
    text = value if isinstance(value, str) else ",".join(value) if isinstance(value, list) else str(value)
    argv = [command, "x.csv", "--robot", "irb120", f"{flag}={text}"]
    with pytest.raises(SystemExit) as refused:
        main(argv + (["--model", "poe", "--out", "y"] if command == "fit" else []))
    assert refused.value.code == 2
    said = capsys.readouterr().err.strip().splitlines()[-1]
    sentence = said.split(f"argument {flag}: ", 1)[1].rsplit(", got ", 1)[0]
    assert message.removeprefix(f"body.{field}: ").removeprefix("Value error, ") == sentence


async def test_a_diagnosis_job_takes_the_command_lines_options_and_records_them(
    client: httpx.AsyncClient, tmp_path: Path
) -> None:
    camp = make_campaign("irb120", 93, [], n_poses=60, repeat_fraction=0.0)
    data = tmp_path / "d.csv"
    write_dataset(camp.dataset, data)
    out = tmp_path / "d.json"
    flags = ["--effects", "ratio", "--compare-models", "none", "--harmonics", "1", "--alpha", "0.01"]
    assert main(["diagnose", str(data), "--robot", "irb120", "--json", str(out), *flags]) == 0
    cli = json.loads(out.read_text())
    dataset_id = await _upload(client, data)
    body = {
        "dataset_id": dataset_id,
        "effects": ["ratio"],
        "compare_models": [],
        "harmonics": 1,
        "alpha": 0.01,
    }
    r = await client.post("/api/diagnoses", json=body, headers=auth("engineer"))
    assert r.status_code == 202, r.text
    params = r.json()["params"]
    assert params["effects"] == ["ratio"] and params["compare_models"] == [] and params["alpha"] == 0.01
    done = await job_done(client, r.json()["id"], limit_s=180.0)
    assert done["state"] == "done", done["error"]
    http = (await client.get(f"/api/diagnoses/{done['id']}", headers=auth("viewer"))).json()
    assert http["method"]["effects_tried"] == cli["method"]["effects_tried"] == ["ratio"]
    assert http["method"] == cli["method"]
    assert http["steps"] == cli["steps"]
    assert "model_comparison" not in http and "model_comparison" not in cli  # compare_models: none


def test_list_options_are_words_on_the_command_line_and_lists_over_http() -> None:
    for effects, compare in (("ratio, drift", "none"), (["ratio", "drift"], [])):
        settings = DiagnosisSettings(effects=effects, compare_models=compare)
        assert settings.effects == ("ratio", "drift") and settings.compare_models == ()
        options = diagnose_options(settings)
        assert options.effects == ("ratio", "drift") and options.compare_models == ()


def test_the_settings_defaults_are_the_documented_methods() -> None:
    assert diagnose_options(DiagnosisSettings()) == DiagnoseOptions()
    assert DiagnoseOptions().compare_models == DiagnosisSettings().compare_models == COMPARED_MODELS


def test_the_service_validates_the_options_without_loading_the_diagnosis() -> None:
    """The request models import nothing of the diagnosis (its numerics load scipy.stats: seconds of
    import and a heavier heap for the service's collector)."""
    code = "import sys, comp_daemon.service.api; print(sorted(m for m in sys.modules if 'diagnosis' in m))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def _parse(command: str, *extra: str) -> Any:
    fit = ["--model", "poe", "--out", "y"] if command == "fit" else []
    return build_parser(command).parse_args([command, "x.csv", "--robot", "kr210", *fit, *extra])


@pytest.mark.parametrize(
    ("command", "settings", "body"),
    [("fit", FitSettings, FitIn), ("diagnose", DiagnosisSettings, DiagnosisIn)],
)
def test_every_setting_is_an_option_of_both_doors(command: str, settings: Any, body: Any) -> None:
    """One field, two doors: each field of the settings is a command-line option with the field's
    default (a flag on by default turned off by ``--no-…``) and a field of the HTTP body."""
    defaults = _parse(command)
    for name, field in settings.model_fields.items():
        assert getattr(defaults, name) == field.default, name
        assert body.model_fields[name].default == field.default, name
        if field.annotation is bool:
            flag = name.replace("_", "-")
            flipped = _parse(command, f"--no-{flag}" if field.default else f"--{flag}")
            assert getattr(flipped, name) is (not field.default), name
