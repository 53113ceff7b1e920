"""The greedy forward selection of effects, with its parsimony and replacement rules.

Every choice is made on the fit rows (:class:`Context`): in each round the candidate with the lowest
k-fold cross-validated error (folds of pose groups) is tested with a cluster-robust Wald test
(:mod:`comp_daemon.diagnosis.stats`); it is significant when its p-value is below ``alpha / m``
(Bonferroni over the m candidates of the round; a candidate whose setting was searched on the fit
rows, the step's moment, has its p-value multiplied by the number of positions tried) and it lowers
the CV error. A runner-up with fewer
parameters that the best does not add to significantly is preferred; after each acceptance every
accepted candidate is offered for replacement by a rejected one. The method is described in full
in :mod:`comp_daemon.diagnosis.ladder`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.diagnosis.candidates import Candidate
from comp_daemon.diagnosis.fitting import (
    FitResult,
    at_fit,
    fit_twin,
    linearize_targets,
    predict_mm,
    project_out,
)
from comp_daemon.diagnosis.result import DiagnoseOptions, rounded
from comp_daemon.diagnosis.stats import LinearProblem, make_folds
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.effects import MassModel
from comp_daemon.models.rows import MeasuredRows

__all__ = ["TIME_NUISANCE_BINS", "Context", "distance_stats", "names_of", "select", "time_nuisance"]

#: the time nuisance translates the TCP by one value per axis in each of this many clock bins
TIME_NUISANCE_BINS = 8

FloatArray = NDArray[np.float64]


def distance_stats(resid: FloatArray) -> tuple[float, float]:
    dist = np.linalg.norm(resid, axis=1)
    if not len(dist):
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(dist**2))), float(dist.max())


class Context:
    """What every step of one diagnosis shares.

    ``nuisance`` (n_fit, 3, q), when set, holds columns that every linear problem carries right after
    the free geometric ones and that no candidate's test may take credit for (the time nuisance of
    :func:`time_nuisance`); :attr:`n_base` counts both blocks.
    """

    def __init__(
        self,
        mass: MassModel,
        obs: MeasuredRows,
        fit_rows: NDArray[np.int64],
        check_rows: NDArray[np.int64],
        geo_free: NDArray[np.bool_],
        options: DiagnoseOptions,
    ) -> None:
        self.mass = mass
        self.obs = obs
        self.fit_rows = fit_rows
        self.check_rows = check_rows
        self.obs_fit = obs.take(fit_rows)
        self.obs_check = obs.take(check_rows)
        self.geo_free = geo_free
        self.geo_idx = np.flatnonzero(geo_free)
        self.options = options
        self.fold = make_folds(self.obs_fit.pose_group, options.folds, options.seed)
        self.nuisance: FloatArray | None = None
        # the TCP's rows (target 0) among the fit and check rows; every row with one target
        self.tcp_fit = _tcp_rows(self.obs_fit)
        self.obs_check_tcp = self.obs_check.take(_tcp_rows(self.obs_check))

    @property
    def n_nuisance(self) -> int:
        return 0 if self.nuisance is None else int(self.nuisance.shape[2])

    @property
    def n_base(self) -> int:
        """Columns before the effect parameters: the free geometric ones and the nuisance."""
        return len(self.geo_idx) + self.n_nuisance

    def own_cols(self, n_names: int) -> list[int]:
        """The columns of the model itself (geometric and ``n_names`` effect parameters), no nuisance."""
        return list(range(len(self.geo_idx))) + list(range(self.n_base, self.n_base + n_names))

    def fit(self, start: FitResult, names: Sequence[str]) -> FitResult:
        return fit_twin(self.mass, self.obs_fit, start.params, start.effects, self.geo_free, names)

    def problem(
        self,
        fit: FitResult,
        names: Sequence[str],
        *,
        tcp_only: bool = False,
        extra: FloatArray | None = None,
    ) -> LinearProblem:
        """Linear problem with columns [free geometric | nuisance | names] at ``fit``; with
        ``tcp_only`` on the TCP's fit rows alone (several targets per pose). The further targets'
        places on the flange are free: their columns are projected out of every column and the
        residual (on the TCP's rows they are zero). ``extra`` (n_fit, 3, q): columns appended after
        the names (a flexible alternative's)."""
        obs = at_fit(self.obs_fit, fit)
        resid, jac, tcols = linearize_targets(self.mass, fit.params, fit.effects, names, obs)
        geo = jac[:, :, self.geo_idx]
        eff = jac[:, :, N_PARAMS + np.arange(len(names))]
        blocks = [geo, eff] if self.nuisance is None else [geo, self.nuisance, eff]
        if extra is not None:
            blocks.append(extra)
        full = np.concatenate(blocks, axis=2)
        if obs.target is not None and not tcp_only:
            resid, full = project_out(tcols, resid, full)
        rows = self.tcp_fit if tcp_only else slice(None)
        return LinearProblem(resid[rows], full[rows], self.obs_fit.pose_group[rows], self.fold[rows])

    def values(self, fit: FitResult, start: KinematicParams, names: Sequence[str]) -> FloatArray:
        """Values of the columns [free geometric | nuisance | names] at ``fit``, measured from ``start``."""
        geo = fit.params.difference(start)[self.geo_idx]
        eff = fit.effects.get(list(names)) if names else np.zeros(0)
        return np.concatenate([geo, np.zeros(self.n_nuisance), eff])

    def check_stats(self, fit: FitResult) -> tuple[float, float]:
        """RMS and maximum of the 3-D error of the TCP (target 0) on the check rows."""
        obs = self.obs_check_tcp
        return distance_stats(obs.xyz_mm - predict_mm(self.mass, fit.params, fit.effects, obs))


def _tcp_rows(obs: MeasuredRows) -> NDArray[np.int64]:
    return np.arange(len(obs)) if obs.target is None else np.flatnonzero(obs.target == 0)


def time_nuisance(clock: FloatArray) -> FloatArray:
    """(n, 3, 3·(B − 1)) columns of a translation that is constant in each of B quantile bins of ``clock``.

    The first bin is left out (the base frame's translation carries the constant). With them in the
    base of every test, an effect cannot take credit for a change over time that correlates with its
    own variable along the campaign's route (a ratio error of A4 standing in for a drift).
    """
    edges = np.unique(np.quantile(clock, np.linspace(0.0, 1.0, TIME_NUISANCE_BINS + 1)[1:-1]))
    bins = np.searchsorted(edges, clock, side="right")
    n_bins = int(bins.max()) + 1
    out = np.zeros((len(clock), 3, 3 * max(n_bins - 1, 0)))
    for b in range(1, n_bins):
        on = (bins == b).astype(float)
        for axis in range(3):
            out[:, axis, 3 * (b - 1) + axis] = on
    return out


def _cols_of(cands: Sequence[Candidate], first: int) -> dict[Candidate, list[int]]:
    out: dict[Candidate, list[int]] = {}
    for c in cands:
        out[c] = list(range(first, first + len(c.names)))
        first += len(c.names)
    return out


def names_of(cands: Sequence[Candidate]) -> list[str]:
    return [n for c in cands for n in c.names]


def select(
    ctx: Context, geo_fit: FitResult, candidates: Sequence[Candidate], options: DiagnoseOptions
) -> tuple[list[Candidate], Candidate | None, list[dict[str, Any]], FitResult]:
    """Greedy forward selection with a replacement pass (see the module docstring).

    Returns the accepted candidates in order, the best rejected one (None if none was left), the
    record of every round, and the fit of the final model.
    """
    avail = list(candidates)
    accepted: list[Candidate] = []
    selection: list[dict[str, Any]] = []
    current = geo_fit
    rejected: Candidate | None = None
    while avail and len(accepted) < options.max_effects:
        lp = ctx.problem(current, names_of(accepted) + names_of(avail))
        base_cols = list(range(ctx.n_base + len(names_of(accepted))))
        col_of = _cols_of(avail, len(base_cols))
        cv_base = lp.cv_rms_mm(base_cols)
        scored = sorted((lp.cv_rms_mm(base_cols + col_of[c]), i) for i, c in enumerate(avail))
        threshold = options.alpha / len(avail)
        ranked: list[dict[str, Any]] = []
        for cv, i in scored[:5]:
            c = avail[i]
            wald = lp.wald(base_cols + col_of[c], col_of[c])
            p_value = min(1.0, wald.p_value * c.searched)
            ranked.append({"candidate": c.label, "cv_rms_mm": rounded(cv), "p_value": p_value})
        best_cv, best_i = scored[0]
        best = avail[best_i]
        best_p = float(ranked[0]["p_value"])
        simpler = _simpler_alternative(
            lp, base_cols, col_of, best, [avail[i] for _, i in scored[1:5]], threshold
        )
        if simpler is not None:
            k = next(k for k, (_, i) in enumerate(scored) if avail[i] is simpler)
            best, best_cv, best_p = simpler, scored[k][0], float(ranked[k]["p_value"])
        significant = best_p < threshold and best_cv < cv_base
        for entry in ranked:
            entry["p_value"] = float(f"{entry['p_value']:.3g}")
        selection.append(
            {
                "round": len(selection) + 1,
                "cv_rms_mm_before": rounded(cv_base),
                "candidates": len(avail),
                "p_threshold": float(f"{threshold:.3g}"),
                "best": ranked,
                "preferred_simpler": None if simpler is None else simpler.label,
                "accepted": best.label if significant else None,
            }
        )
        if not significant:
            rejected = best
            break
        accepted.append(best)
        avail.remove(best)
        current = ctx.fit(current, names_of(accepted))
        current = _replace_pass(ctx, current, accepted, avail, options, selection)
    return accepted, rejected, selection, current


def _simpler_alternative(
    lp: LinearProblem,
    base_cols: list[int],
    col_of: dict[Candidate, list[int]],
    best: Candidate,
    runners_up: Sequence[Candidate],
    threshold: float,
) -> Candidate | None:
    """A runner-up with fewer parameters that ``best`` does not significantly improve on, if any.

    Over a limited range of a joint, a few harmonics reproduce a linear ratio error almost exactly,
    and cross-validation cannot tell the two apart; parsimony can: the larger candidate must add
    to the smaller one at the selection's own significance threshold, or the smaller one is taken.
    """
    for c in runners_up:  # in order of CV error
        if len(c.names) >= len(best.names):
            continue
        if lp.wald(base_cols + col_of[c] + col_of[best], col_of[best]).p_value >= threshold:
            return c
    return None


def _replace_pass(
    ctx: Context,
    current: FitResult,
    accepted: list[Candidate],
    avail: list[Candidate],
    options: DiagnoseOptions,
    selection: list[dict[str, Any]],
) -> FitResult:
    """Replace an accepted candidate by a rejected one while that lowers the CV error.

    Forward selection can take a candidate that stood in for two true effects at once (a cyclic
    term absorbing a ratio error and part of a thermal drift); once the second one is in, the
    first may be better explained by another candidate. Each accepted candidate is taken out (its
    parameters set to zero, the problem linearised there), and the best replacement by CV must beat
    it and pass the same significance test. Changes are recorded in ``selection``.
    """
    for _ in range(3 * max(len(accepted), 1)):
        swapped = False
        for k, old in enumerate(accepted):
            others = [c for c in accepted if c is not old]
            point = dataclasses.replace(
                current,
                effects=current.effects.with_values(list(old.names), np.zeros(len(old.names))),
                iterations=0,
                converged=True,
            )
            pool = [old, *avail]
            lp = ctx.problem(point, names_of(others) + names_of(pool))
            base_cols = list(range(ctx.n_base + len(names_of(others))))
            col_of = _cols_of(pool, len(base_cols))
            cv_old = lp.cv_rms_mm(base_cols + col_of[old])
            cv_new, i = min((lp.cv_rms_mm(base_cols + col_of[c]), i) for i, c in enumerate(avail))
            new = avail[i]
            if cv_new >= cv_old:
                continue
            p_value = min(1.0, lp.wald(base_cols + col_of[new], col_of[new]).p_value * new.searched)
            if p_value >= options.alpha / len(pool):
                continue
            if len(new.names) > len(old.names):
                both = base_cols + col_of[old] + col_of[new]
                if lp.wald(both, col_of[new]).p_value >= options.alpha / len(pool):
                    continue  # the larger candidate does not add to the smaller one: keep the smaller
            selection.append(
                {
                    "round": len(selection) + 1,
                    "replaced": old.label,
                    "by": new.label,
                    "cv_rms_mm_before": rounded(cv_old),
                    "cv_rms_mm_after": rounded(cv_new),
                    "p_value": float(f"{p_value:.3g}"),
                }
            )
            accepted[k] = new
            avail[i] = old
            current = ctx.fit(point, names_of(accepted))
            swapped = True
            break
        if not swapped:
            break
    return current
