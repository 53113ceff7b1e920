"""The sizes of the effects: one store for every parameter array of the catalogue, and their names.

:class:`EffectParams` holds, for each :class:`~comp_daemon.models.effects.base.ParamArray` of
:data:`~comp_daemon.models.effects.catalogue.EFFECT_CATALOGUE`, an array under its ``attr``
(``backlash_deg``, ``ratio``, ``cyclic_sin_deg`` …; index 0 = joint 1), readable as an attribute
and settable as a keyword of the constructor (or of :func:`dataclasses.replace`). Per-joint arrays
have shape (6,), harmonic arrays (6, K) with one K shared by all of them (0 allowed), scalars are
floats. Zeros are no effect. ``t_ref_c`` is the reference temperature of the thermal growth;
``step_at`` the campaign clock value from which the step effect acts (infinite: never).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache, lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.models.effects.base import N_JOINTS, Effect, ParamArray, ParamRef
from comp_daemon.models.effects.catalogue import EFFECT_CATALOGUE, EFFECTS, effect_by_name

__all__ = ["EffectParams", "effect_param_names", "parse_param_name"]

_NAME_RE = re.compile(r"^([A-Za-z]+)(?:([0-9]+)(?:_([0-9]+))?)?$")


@cache
def _arrays() -> dict[str, tuple[Effect, int, ParamArray]]:
    """attr -> (effect, index of the array in the effect, array), in catalogue order."""
    return {arr.attr: (e, i, arr) for e in EFFECT_CATALOGUE for i, arr in enumerate(e.arrays)}


@cache
def _symbols() -> dict[str, tuple[Effect, int, ParamArray]]:
    return {entry[2].symbol: entry for entry in _arrays().values()}


def _unknown(name: str) -> ValueError:
    patterns = ", ".join(arr.pattern for _, _, arr in _arrays().values())
    return ValueError(f"unknown effect parameter '{name}' (expected {patterns})")


@lru_cache(maxsize=4096)  # a fit parses the same few names at every residual
def parse_param_name(name: str, n_harmonics: int) -> ParamRef:
    """Where the parameter ``name`` lives; ValueError for an unknown name or a harmonic beyond K."""
    m = _NAME_RE.match(name)
    entry = _symbols().get(m.group(1)) if m else None
    if m is None or entry is None:
        raise _unknown(name)
    effect, index, arr = entry
    joint, harmonic = m.group(2), m.group(3)
    shape_ok = {
        "joint": joint is not None and harmonic is None,
        "harmonic": joint is not None and harmonic is not None,
        "scalar": joint is None,
    }[arr.layout]
    if not shape_ok or (joint is not None and not 1 <= int(joint) <= N_JOINTS):
        raise _unknown(name)
    if harmonic is not None and not 1 <= int(harmonic) <= n_harmonics:
        raise ValueError(
            f"effect parameter '{name}': harmonic {harmonic} exceeds the {n_harmonics} "
            "harmonics of these effect parameters"
        )
    return ParamRef(
        effect=effect,
        array=index,
        joint=None if joint is None else int(joint) - 1,
        harmonic=None if harmonic is None else int(harmonic) - 1,
    )


def _checked(arr: ParamArray, value: Any) -> Any:
    """``value`` as the array ``arr`` stores it (validated); a float for a scalar."""
    if arr.layout == "scalar":
        out = float(value)
        if not np.isfinite(out):
            raise ValueError(f"EffectParams.{arr.attr}: must be finite, got {out}")
        return out
    a = np.array(value, dtype=float)
    if arr.layout == "joint":
        if a.shape == ():
            a = np.full(N_JOINTS, float(a))
        if a.shape != (N_JOINTS,):
            raise ValueError(
                f"EffectParams.{arr.attr}: expected 6 values (one per joint), got shape {a.shape}"
            )
    elif a.ndim != 2 or a.shape[0] != N_JOINTS:
        raise ValueError(f"EffectParams.{arr.attr}: expected shape (6, K), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"EffectParams.{arr.attr}: values must be finite")
    return a


def _zeros(arr: ParamArray, n_harmonics: int) -> Any:
    if arr.layout == "scalar":
        return 0.0
    return np.zeros(N_JOINTS) if arr.layout == "joint" else np.zeros((N_JOINTS, n_harmonics))


@dataclass(frozen=True, slots=True, init=False, eq=False)
class EffectParams:
    """Sizes of the non-geometric effects (see the module docstring). Zeros are no effect.

    ``EffectParams(backlash_deg=..., thermal_per_k=..., t_ref_c=...)``: every array not given is
    zero; ``arrays`` (a mapping attr -> value) gives a starting set that the keywords override.
    """

    arrays: Mapping[str, Any]
    t_ref_c: float
    step_at: float

    def __init__(
        self,
        *,
        t_ref_c: float = 20.0,
        step_at: float = float("inf"),
        arrays: Mapping[str, Any] | None = None,
        **given: Any,
    ):
        known = _arrays()
        bad = [k for k in given if k not in known]
        if bad:
            raise TypeError(
                f"EffectParams: unknown parameter array(s) {', '.join(bad)} (known: {', '.join(known)})"
            )
        merged = {**(arrays or {}), **given}
        harmonic = [a for a, (_, _, arr) in known.items() if arr.layout == "harmonic"]
        # an array not given is zero with K = 0 harmonics, so all of them must be given together
        ks = {int(np.shape(merged[a])[1]) if np.ndim(merged[a]) == 2 else -1 for a in harmonic if a in merged}
        if any(a not in merged for a in harmonic):
            ks.add(0)
        if len(ks) > 1:
            shapes = ", ".join(
                f"{a} {np.shape(merged[a]) if a in merged else (N_JOINTS, 0)}" for a in harmonic
            )
            raise ValueError(
                f"EffectParams: the harmonic arrays must all have shape (6, K) with one K, got {shapes}"
            )
        k = max(ks, default=0)
        store = {
            attr: _checked(arr, merged[attr]) if attr in merged else _zeros(arr, k)
            for attr, (_, _, arr) in known.items()
        }
        t_ref = float(t_ref_c)
        if not np.isfinite(t_ref):
            raise ValueError(f"EffectParams.t_ref_c: must be finite, got {t_ref}")
        object.__setattr__(self, "arrays", store)
        step = float(step_at)
        if np.isnan(step):
            raise ValueError("EffectParams.step_at: must be a number (inf: no step), got nan")
        object.__setattr__(self, "t_ref_c", t_ref)
        object.__setattr__(self, "step_at", step)

    def __getattr__(self, name: str) -> Any:
        try:
            arrays = object.__getattribute__(self, "arrays")
        except AttributeError:
            raise AttributeError(name) from None
        if name in arrays:
            return arrays[name]
        raise AttributeError(f"'EffectParams' object has no attribute '{name}'")

    @classmethod
    def zeros(
        cls, n_harmonics: int = 0, t_ref_c: float = 20.0, step_at: float = float("inf")
    ) -> EffectParams:
        """No effect at all, with room for ``n_harmonics`` harmonics in every harmonic array."""
        if n_harmonics < 0:
            raise ValueError(f"n_harmonics must be >= 0, got {n_harmonics}")
        return cls(
            t_ref_c=t_ref_c,
            step_at=step_at,
            arrays={a: _zeros(arr, n_harmonics) for a, (_, _, arr) in _arrays().items()},
        )

    @property
    def n_harmonics(self) -> int:
        for attr, (_, _, arr) in _arrays().items():
            if arr.layout == "harmonic":
                return int(self.arrays[attr].shape[1])
        return 0

    def of(self, effect: Effect) -> tuple[Any, ...]:
        """The values of ``effect``'s arrays, in the order of ``effect.arrays``."""
        return tuple(self.arrays[arr.attr] for arr in effect.arrays)

    def is_zero(self, effect: Effect) -> bool:
        """True when every parameter of ``effect`` is zero (the effect is absent)."""
        return all(not np.any(np.asarray(v) != 0.0) for v in self.of(effect))

    def names(
        self, effects: Sequence[str] = EFFECTS, joints: Sequence[int] = (1, 2, 3, 4, 5, 6)
    ) -> list[str]:
        """Parameter names of ``effects`` on ``joints`` with this object's number of harmonics."""
        return effect_param_names(effects, joints, self.n_harmonics)

    def _ref(self, name: str) -> ParamRef:
        return parse_param_name(name, self.n_harmonics)

    def get(self, names: Sequence[str]) -> NDArray[np.float64]:
        """Values of the named parameters (units as in the catalogue)."""
        out = np.empty(len(names))
        for index, name in enumerate(names):
            ref = self._ref(name)
            value = self.arrays[ref.effect.arrays[ref.array].attr]
            out[index] = _element(value, ref)
        return out

    def with_values(
        self, names: Sequence[str], values: NDArray[np.float64] | Sequence[float]
    ) -> EffectParams:
        """A copy with the named parameters set to ``values``."""
        values = np.asarray(values, dtype=float)
        if values.shape != (len(names),):
            raise ValueError(f"{len(names)} names but values of shape {values.shape}")
        store: dict[str, Any] = {a: (v if isinstance(v, float) else v.copy()) for a, v in self.arrays.items()}
        for name, value in zip(names, values, strict=True):
            ref = self._ref(name)
            attr = ref.effect.arrays[ref.array].attr
            if ref.joint is None:
                store[attr] = float(value)
            elif ref.harmonic is None:
                store[attr][ref.joint] = value
            else:
                store[attr][ref.joint, ref.harmonic] = value
        return EffectParams(t_ref_c=self.t_ref_c, step_at=self.step_at, arrays=store)

    def add(self, names: Sequence[str], delta: NDArray[np.float64] | Sequence[float]) -> EffectParams:
        """A copy with ``delta`` added to the named parameters (an identification step)."""
        return self.with_values(names, self.get(names) + np.asarray(delta, dtype=float))


def _element(value: Any, ref: ParamRef) -> float:
    if ref.joint is None:
        return float(value)
    if ref.harmonic is None:
        return float(value[ref.joint])
    return float(value[ref.joint, ref.harmonic])


def effect_param_names(
    effects: str | Sequence[str], joints: Sequence[int] = (1, 2, 3, 4, 5, 6), n_harmonics: int = 0
) -> list[str]:
    """Parameter names of the given effect(s) (docs/diagnosis-output.md) on the given joints (1-based).

    A scalar parameter (``kappa`` of ``thermal``) has one name whatever the joints; an effect with
    several arrays gives, per joint, each array's names in turn (``cyclic``: ``c{j}_{k}`` then
    ``s{j}_{k}`` for k = 1..n_harmonics).
    """
    if isinstance(effects, str):
        effects = (effects,)
    for j in joints:
        if not 1 <= int(j) <= N_JOINTS:
            raise ValueError(f"joint {j}: joints are numbered 1..6")
    names: list[str] = []
    for name in effects:
        names += effect_by_name(name).names([int(j) for j in joints], n_harmonics)
    return names
