"""A model kind is one module: its model class, its fit function and its registry entry together,
the entries listed once (the registry's), and the ErrorModel doors written once (base.py)."""

from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

import numpy as np
import pytest

import comp_daemon
from comp_daemon.models.base import ErrorModel, Query
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.registry import ALL_MODELS, ARTIFACT_KINDS, KINDS, model_from_payload
from comp_daemon.robot.description import load_robot

PACKAGE = Path(comp_daemon.__file__).parent
KIND_NAMES = set(KINDS)
#: the ErrorModel methods every caller uses, written once in base.py
DOORS = ("predict_tcp_mm", "predict_std_mm", "from_payload")


@pytest.mark.parametrize("name", list(KINDS))
def test_a_kinds_class_fit_and_entry_live_in_one_module(name: str) -> None:
    """The entry is a module-level name of the module that defines the fit function, and the
    model class is that module's, or (``kinematic_kind``) the one it sits beside."""
    kind = KINDS[name]
    home = importlib.import_module(kind.fit.__module__)
    entries = [v for v in vars(home).values() if isinstance(v, ModelKind)]
    assert any(e is kind for e in entries), f"{name}: the entry is not declared in {home.__name__}"
    assert kind.model_class.__module__ in (home.__name__, home.__name__.removesuffix("_kind")), name
    # and the module declares no entry the registry does not list
    assert all(e in KINDS.values() for e in entries), home.__name__


def test_the_registry_lists_every_entry_a_kind_module_declares() -> None:
    """A new kind's module with its KIND but no line in the registry's list is caught here."""
    listed = {id(k) for k in KINDS.values()}
    models = PACKAGE / "models"
    for path in sorted(models.rglob("*.py")):
        module = importlib.import_module(
            "comp_daemon." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts)
        )
        for value in vars(module).values():
            if isinstance(value, ModelKind):
                assert id(value) in listed, f"{module.__name__} declares {value.name}, the registry omits it"


def _string_lists(tree: ast.AST) -> list[tuple[int, list[str]]]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Tuple | ast.List | ast.Set):
            words = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
            out.append((node.lineno, words))
    return out


def test_no_kind_list_is_written_by_hand_outside_the_registry() -> None:
    """The schemas, the artifact loader, the commands read KINDS / ARTIFACT_KINDS: a literal list of
    three or more kind names anywhere else would drift from them (as `poe` once did)."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path == PACKAGE / "models" / "registry.py":
            continue
        for line, words in _string_lists(ast.parse(path.read_text("utf-8"))):
            named = {w for w in words if w in KIND_NAMES}
            if len(named) >= 3:
                found.append(f"{path.relative_to(PACKAGE)}:{line}: {sorted(named)}")
    assert not found, found


def test_the_registrys_own_lists_derive_from_its_entries() -> None:
    assert set(ARTIFACT_KINDS) == {k.model_class.kind for k in KINDS.values()}
    assert all(ARTIFACT_KINDS[k.model_class.kind] is k.model_class for k in KINDS.values())
    assert {name.split("+")[0].split(":")[0] for name in ALL_MODELS} == KIND_NAMES


@pytest.mark.parametrize("name", list(KINDS))
def test_no_kind_rewrites_the_error_model_doors(name: str) -> None:
    """A kind implements tcp_mm / from_stored (and std_mm, parameter_jacobian where it has its own);
    the doors with their signatures are the base class's."""
    cls = KINDS[name].model_class
    for klass in cls.__mro__:
        if klass is ErrorModel:
            break
        overridden = set(DOORS) & set(vars(klass))
        assert not overridden, f"{klass.__name__} rewrites {sorted(overridden)}"
    assert not inspect.isabstract(cls)


def test_the_doors_normalise_a_single_pose_and_a_missing_payload() -> None:
    """One pose as (6,) and payload None reach tcp_mm as (1, 6) and 0.0, for every kind."""
    robot = load_robot("kr210")
    seen: list[Query] = []

    class Probe(ErrorModel):
        kind = "probe"

        def __init__(self) -> None:
            self.robot = robot
            self.world_T_base = self.registration = np.eye(4)

        def tcp_mm(self, query: Query) -> np.ndarray:
            seen.append(query)
            return np.zeros((query.a.shape[0], 3))

        def to_payload(self) -> dict[str, object]:
            return {}

        @classmethod
        def from_stored(cls, stored: object) -> Probe:
            return cls()

    model = Probe()
    assert model.predict_tcp_mm(np.zeros(6)).shape == (1, 3)
    assert seen[-1].a.shape == (1, 6) and seen[-1].payload_kg == 0.0
    assert model.predict_std_mm(np.zeros((2, 6))) is None
    with pytest.raises(ValueError, match="no parameter covariance for a probe model"):
        model.parameter_jacobian(("x",), np.zeros(1), seen[-1])
    assert isinstance(Probe.from_payload(robot, {}, None, np.eye(4)), Probe)


def test_a_stored_kriging_base_is_rebuilt_through_the_registry() -> None:
    """The kriging model's base comes back through the loader the registry hands it (no per-kind hook)."""
    robot = load_robot("kr210")
    with pytest.raises(ValueError, match="cannot stand on a base model of kind 'kriging'"):
        model_from_payload("kriging", robot, {"base": {"kind": "kriging", "order": None}}, None, np.eye(4))
    with pytest.raises(ValueError, match="unknown model kind 'spline'"):
        model_from_payload(
            "kriging",
            robot,
            {"base": {"kind": "spline", "order": None, "model": {}, "registration": np.eye(4).tolist()}},
            None,
            np.eye(4),
        )
