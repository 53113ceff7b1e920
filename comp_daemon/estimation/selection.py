"""Which parts of a model earn their place: out-of-fold selection on the fit rows.

A model kind with effects (``kinematic+ratio+backlash``, ``kriging-backlash``, ``compliance``, …)
adds parameters for errors that a campaign may not have. Where an effect is absent its parameters
fit the noise of the fit rows and cost accuracy on new poses. Each part beyond the kinematic
geometry is therefore kept only if it lowers the error on rows it was not fitted on — on the fit
rows alone, the check rows are never seen.

The rule. For a part ``e`` and the model without it, let ``g_i = |err_i(without)|² − |err_i(with)|²``
be the per-row gain in the squared 3-D error of held-out predictions (K-fold cross-validation on the
fit rows for parametric effects; the leave-one-out prediction against no prediction for a kriging
stage). The part is kept when the mean gain exceeds twice its standard error,
``mean(g) > Z·sd(g)/√n`` with ``Z`` = :data:`Z_KEEP` = 2 — a one-sided test at about 2 %: a part
whose gain cannot be told from the spread of its own estimate goes, and ties go to the simpler
model. (With ``Z = 1``, the one-standard-error rule, an absent effect passes with a probability of
about 0.16; an absent backlash did, on a simulated campaign with geometric errors only.)

Effects are eliminated backwards: from the full set, the part with the smallest gain among those
that do not earn their place is dropped and the remaining set is judged again, until every part
left earns its place (:func:`select_kinematic_effects`). :func:`judge` is the rule for one part.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.estimation import steps

__all__ = [
    "RULE",
    "Z_KEEP",
    "Decision",
    "Selection",
    "fold_indices",
    "judge",
    "keep_all",
    "select_kinematic_effects",
    "selection_line",
]

log = get_logger(__name__)

Z_KEEP = 2.0  # standard errors the mean gain must exceed
RULE = "kept when the mean out-of-fold gain in squared 3-D error exceeds twice its standard error"
MIN_ROWS_PER_FOLD = 8  # fewer fit rows than folds × this: no selection, every part kept


@dataclass(frozen=True, slots=True)
class Decision:
    """What was decided about one part of a model, and on what numbers."""

    part: str  # an effect name ("backlash"), or "kriging", "anisotropic ranges"
    kept: bool
    gain_mm2: float  # mean per-row gain in squared held-out 3-D error (mm²) with the part
    se_mm2: float  # its standard error
    rms_with_mm: float  # held-out 3-D RMS with the part
    rms_without_mm: float  # and without it
    method: str  # "5-fold cross-validation on the fit rows", "leave-one-out on 180 samples", …

    @property
    def reason(self) -> str:
        verdict = "kept" if self.kept else "dropped"
        relation = ">" if self.kept else "<="
        return (
            f"{self.part} {verdict}: held-out 3-D RMS {self.rms_with_mm:.4f} mm with it, "
            f"{self.rms_without_mm:.4f} mm without; mean gain {self.gain_mm2:.3g} mm² {relation} "
            f"{Z_KEEP:g} × its standard error {self.se_mm2:.3g} mm² ({self.method})"
        )

    def to_info(self) -> dict[str, Any]:
        return {
            "part": self.part,
            "kept": self.kept,
            "gain_mm2": self.gain_mm2,
            "se_mm2": self.se_mm2,
            "rms_with_mm": self.rms_with_mm,
            "rms_without_mm": self.rms_without_mm,
            "method": self.method,
            "reason": self.reason,
        }


@dataclass(frozen=True, slots=True)
class Selection:
    """The parts a fit kept and dropped (``decisions`` in the order they were made)."""

    kept: tuple[str, ...]
    dropped: tuple[str, ...]
    decisions: tuple[Decision, ...]
    note: str | None = None  # why no selection was made, when none was

    def to_info(self) -> dict[str, Any]:
        return {
            "rule": RULE,
            "kept": list(self.kept),
            "dropped": list(self.dropped),
            "decisions": [d.to_info() for d in self.decisions],
            "note": self.note,
        }

    def summary(self) -> str:
        """One line: what was kept and dropped."""
        if self.note is not None:
            return self.note
        kept = ", ".join(self.kept) or "none"
        dropped = ", ".join(self.dropped) or "none"
        return f"kept {kept}; dropped {dropped}"

    def __add__(self, other: Selection) -> Selection:
        notes = [n for n in (self.note, other.note) if n]
        return Selection(
            self.kept + other.kept,
            self.dropped + other.dropped,
            self.decisions + other.decisions,
            "; ".join(notes) if notes else None,
        )


def judge(
    part: str, err2_with: NDArray[np.float64], err2_without: NDArray[np.float64], method: str
) -> Decision:
    """The rule of the module docstring for one part: per-row held-out squared 3-D errors with and
    without it (same rows)."""
    w = np.asarray(err2_with, dtype=float)
    wo = np.asarray(err2_without, dtype=float)
    gain = wo - w
    n = gain.size
    mean = float(gain.mean())
    se = float(gain.std(ddof=1) / np.sqrt(n)) if n > 1 else float("inf")
    return Decision(
        part=part,
        kept=bool(mean > Z_KEEP * se),
        gain_mm2=mean,
        se_mm2=se,
        rms_with_mm=float(np.sqrt(w.mean())),
        rms_without_mm=float(np.sqrt(wo.mean())),
        method=method,
    )


def fold_indices(n: int, folds: int, seed: int) -> list[NDArray[np.intp]]:
    """The held-out rows of each of ``folds`` folds of ``n`` rows, drawn reproducibly."""
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(f) for f in np.array_split(perm, folds)]


Model = TypeVar("Model")
"""Whatever ``fit_on`` returns and ``errors_of`` takes: the caller's fitted model."""


def select_kinematic_effects(
    effects: Sequence[str],
    n_rows: int,
    fit_on: Callable[[Sequence[str], NDArray[np.intp]], Model],
    errors_of: Callable[[Model, NDArray[np.intp]], NDArray[np.float64]],
    *,
    folds: int,
    seed: int,
    protected: Sequence[str] = (),
    of_rows: int | None = None,
) -> tuple[tuple[str, ...], Selection]:
    """Backward elimination of ``effects`` by the rule (module docstring).

    ``fit_on(effects, rows)`` fits the model with those effects on the fit rows ``rows``;
    ``errors_of(model, rows)`` gives its (len(rows), 3) errors on the held-out ``rows``. Effects in
    ``protected`` are never dropped; ``of_rows`` is how many fit rows the ``n_rows`` were drawn
    from, when they are a subset (it goes into the decisions' method). Returns the effects kept
    (in their given order) and the selection.
    """
    candidates = [e for e in effects if e not in protected]
    if not candidates:
        return tuple(effects), Selection(tuple(effects), (), ())
    k = min(folds, n_rows)
    if k < 2 or n_rows < k * MIN_ROWS_PER_FOLD:
        note = (
            f"no selection: {n_rows} fit rows are too few for {folds}-fold cross-validation "
            f"(at least {folds * MIN_ROWS_PER_FOLD}); every effect kept"
        )
        return tuple(effects), Selection(tuple(effects), (), (), note)
    held_out = fold_indices(n_rows, k, seed)
    every = np.arange(n_rows)
    of = "the" if of_rows is None or of_rows == n_rows else f"{n_rows} of the"
    method = f"{k}-fold cross-validation on {of} {of_rows or n_rows} fit rows"
    cache: dict[tuple[str, ...], NDArray[np.float64]] = {}
    fits = {"done": 0, "known": 0}  # cross-validation fits made, and those known to be needed

    def key_of(subset: Sequence[str]) -> tuple[str, ...]:
        return tuple(e for e in effects if e in subset)

    def cv(subset: Sequence[str]) -> NDArray[np.float64]:
        key = key_of(subset)
        if key not in cache:
            err2 = np.empty(n_rows)
            for rows in held_out:
                model = fit_on(key, np.setdiff1d(every, rows))
                err2[rows] = np.sum(errors_of(model, rows) ** 2, axis=1)
                fits["done"] += 1
                steps.report("cross-validation fits", fits["done"], fits["known"])
            cache[key] = err2
        return cache[key]

    current = list(effects)
    decisions: list[Decision] = []
    dropped: list[str] = []
    while True:
        removable = [e for e in current if e not in protected]
        if not removable:
            break
        this_round = {key_of(current), *(key_of([x for x in current if x != e]) for e in removable)}
        fits["known"] += k * len(this_round - cache.keys())
        with_all = cv(current)
        verdicts = [judge(e, with_all, cv([x for x in current if x != e]), method) for e in removable]
        losers = [d for d in verdicts if not d.kept]
        if not losers:
            decisions += verdicts
            break
        worst = min(losers, key=lambda d: d.gain_mm2)
        decisions.append(worst)
        dropped.append(worst.part)
        current.remove(worst.part)
        log.debug("effect dropped", reason=worst.reason)
    kept = tuple(e for e in effects if e in current)
    return kept, Selection(kept, tuple(dropped), tuple(decisions))


def keep_all(parts: Sequence[str]) -> Selection:
    """Every part kept because the model name asks for it (``:all``, the papers' forms)."""
    return Selection(tuple(parts), (), (), "every effect kept, no selection (the paper's form)")


def selection_line(info: dict[str, Any]) -> str | None:
    """One line for a fit summary's ``selection`` entry: what was kept and dropped, each dropped
    part with its held-out RMS without and with it; None when there was nothing to select."""
    sel = info.get("selection")
    if not sel or (not sel["kept"] and not sel["dropped"]):
        return None
    if sel.get("note"):
        return str(sel["note"])
    dropped = [f"{d['part']} ({_held_out(d)})" for d in sel["decisions"] if not d["kept"]]
    return f"kept {', '.join(sel['kept']) or 'no effect'}; dropped {', '.join(dropped) or 'none'}"


def _held_out(d: dict[str, Any]) -> str:
    """A dropped part's held-out RMS without and with it, and why a lower RMS with it did not keep it."""
    text = f"{d['rms_without_mm']:.4f} mm held out without, {d['rms_with_mm']:.4f} with"
    if d["rms_with_mm"] < d["rms_without_mm"]:
        text += f": a gain within {Z_KEEP:g} standard errors, not kept"
    return text
