"""Configuration: config.example.toml names and documents every setting; TOML + environment loading."""

from __future__ import annotations

import shutil
import tomllib
import typing
from pathlib import Path
from typing import Any

import pydantic
import pytest
from pydantic import BaseModel

from comp_daemon.service.config import Settings, load_settings

EXAMPLE = Path(__file__).resolve().parents[1] / "config.example.toml"


def _model_of(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model inside an annotation (``X``, ``list[X]``, ``X | None``), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _model_of(arg)
        if found is not None:
            return found
    return None


def _field_paths(model: type[BaseModel], prefix: str = "") -> set[str]:
    out: set[str] = set()
    for name, info in model.model_fields.items():
        path = f"{prefix}{name}"
        sub = _model_of(info.annotation)
        if sub is None:
            out.add(path)
        else:
            out |= _field_paths(sub, f"{path}.")
    return out


def _toml_paths(value: Any, prefix: str = "") -> set[str]:
    out: set[str] = set()
    if isinstance(value, dict):
        for key, item in value.items():
            path = f"{prefix}{key}"
            if isinstance(item, dict) or (isinstance(item, list) and item and isinstance(item[0], dict)):
                out |= _toml_paths(item, f"{path}.")
            else:
                out.add(path)
    elif isinstance(value, list):
        for item in value:
            out |= _toml_paths(item, prefix)
    return out


def test_example_names_every_setting() -> None:
    doc = tomllib.loads(EXAMPLE.read_text(encoding="utf-8"))
    fields = _field_paths(Settings)
    named = _toml_paths(doc)
    assert fields - named == set(), f"settings missing from config.example.toml: {sorted(fields - named)}"
    assert named - fields == set(), (
        f"keys in config.example.toml that are no setting: {sorted(named - fields)}"
    )


def test_example_comments_every_key() -> None:
    lines = EXAMPLE.read_text(encoding="utf-8").splitlines()
    for i, line in enumerate(lines):
        stripped = line.strip()
        if not stripped or stripped.startswith("#") or stripped.startswith("["):
            continue
        assert "=" in stripped, f"line {i + 1}: {line!r}"
        previous = lines[i - 1].strip() if i else ""
        assert previous.startswith("#"), (
            f"line {i + 1} ({stripped.split('=')[0].strip()}) has no comment above it"
        )


def _example_in(tmp_path: Path) -> Path:
    config = tmp_path / "config.toml"
    shutil.copy(EXAMPLE, config)
    (tmp_path / "engineer.token").write_text("engineer-secret-from-a-file-0123\n", encoding="utf-8")
    return config


def test_example_loads_with_documented_values(tmp_path: Path) -> None:
    settings = load_settings(_example_in(tmp_path))
    assert settings.rsi.cycle_ms == 12
    assert settings.controller.kp == 0.05 and settings.controller.kd == 0.65
    assert settings.controller.rough_step_deg == 0.002 and settings.controller.rough_threshold_deg == 0.007
    assert [j.joint for j in settings.encoders.joints] == [1, 2, 3]
    assert all(j.resolution_nm == 50.0 for j in settings.encoders.joints)
    # relative paths are relative to the file's folder; a token file's content is the secret
    assert settings.store.data_dir == tmp_path / "var"
    engineer = next(t for t in settings.auth.tokens if t.name == "calibration")
    assert engineer.secret == "engineer-secret-from-a-file-0123"
    assert engineer.token_file == tmp_path / "engineer.token"
    # defaults of the model agree with the example (the example documents the defaults)
    defaults = Settings()
    for section in ("http", "jobs", "controller", "log"):
        assert getattr(settings, section) == getattr(defaults, section), section


def test_environment_overrides_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = _example_in(tmp_path)
    monkeypatch.setenv("COMP_DAEMON_HTTP__PORT", "9123")
    monkeypatch.setenv("COMP_DAEMON_RSI__CYCLE_MS", "4")
    monkeypatch.setenv("COMP_DAEMON_RSI__CONTROLLER_ALLOW", '["10.0.0.7"]')
    settings = load_settings(config)
    assert settings.http.port == 9123
    assert settings.rsi.cycle_ms == 4
    assert settings.rsi.controller_allow == ["10.0.0.7"]
    assert settings.http.host == "127.0.0.1"  # untouched keys keep the file's values


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("[http]\nprot = 1\n", "prot"),
        ("[rsi]\ncycle_ms = 10\n", "cycle_ms"),
        ("[rsi]\ncontroller_allow = ['not-an-ip']\n", "not an IP address"),
        ("[[auth.tokens]]\nname='a'\nrole='viewer'\ntoken='short'\n", "at least 16 characters"),
        ("[[auth.tokens]]\nname='a'\nrole='admin'\ntoken='0123456789abcdefgh'\n", "role"),
        ("[[auth.tokens]]\nname='a'\nrole='viewer'\ntoken_file='missing.token'\n", "cannot read token_file"),
        ("[controller]\nsettle_tolerance_deg = 0.01\n", "settle_tolerance_deg"),
        # keys of earlier versions: named, with the reason, not ignored
        ("[realtime]\nmode = 'process'\n", "realtime.mode is no longer a setting"),
        ("[realtime]\nthread = true\n", "realtime.thread is no longer a setting"),
        ("[realtime]\nswitch_interval_ms = 0.2\n", "realtime.switch_interval_ms is no longer a setting"),
        ("[realtime]\ncpu = -1\n", "a CPU number is 0 or more"),
        (
            "[[encoders.joints]]\njoint=1\nport='a'\nradius_mm=1\n[[encoders.joints]]\njoint=1\nport='b'\nradius_mm=1\n",
            "one grating",
        ),
    ],
)
def test_bad_settings_are_refused_by_name(tmp_path: Path, text: str, fragment: str) -> None:
    config = tmp_path / "bad.toml"
    config.write_text(text, encoding="utf-8")
    with pytest.raises(pydantic.ValidationError) as info:
        load_settings(config)
    assert fragment in str(info.value)


def test_missing_file_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        load_settings(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[http\nport = 1\n", encoding="utf-8")
    with pytest.raises(tomllib.TOMLDecodeError):
        load_settings(bad)


def test_annotations_cover_unions() -> None:
    # the walker above must see through list[...] and X | None, or the coverage test proves nothing
    assert _model_of(list[Settings]) is Settings
    assert _model_of(Settings | None) is Settings
    assert _model_of(int | None) is None
    assert "auth.tokens.token_file" in _field_paths(Settings)
    assert "encoders.joints.radius_mm" in _field_paths(Settings)
