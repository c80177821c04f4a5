"""The rescan search with several pose models: the ranking on their mean, the keep rule on their disagreement.

Why (issue 29, docs/recommend-verified.md): pose models trained alike but from different seeds each make, now and
then, a confident wrong prediction for one set-up (a turned head on a region already near its best), and which
set-up depends on the seed; no seed chosen on regions of its own avoids it on regions it has not seen. Where one
member is wrong the others mostly are not, so their disagreement is the part of the prediction's uncertainty a
single model cannot see about itself (the epistemic part; a deep ensemble).

:func:`recommend_ensemble` runs :func:`recommend.recommend` with each member (its own U, domain and calibration,
``keep_current`` off), keeps the candidates every member evaluated (in every member's domain), and gives each
the members' mean figures (``score_unc_mm`` their root mean square, ``out_of_domain`` their largest). It ranks on
the mean. The keep rule: member i predicts the gain ``g_i`` of the best-ranked candidate over the current set-up,
with its own uncertainty ``u_i`` (:func:`recommend.gain_and_uncertainty`, the member's ``k``); the change is advised
only when ``mean(g) > sqrt(mean(u²) + var(g))`` (``var`` with M − 1), else "keep the current set-up". With one
member, or members that agree, it is the single model's rule.

:func:`search` is the entry point of the node and the tools: :func:`recommend_ensemble` for a
:class:`SearchEnsemble`, :func:`recommend.recommend` for one model set. :class:`SearchEnsemble` holds the members
(inference ``ModelSet``s sharing the primary's features); :func:`load_search_ensemble` loads every sub-directory of
a directory that holds a model card.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .recommend import (
    FROM_MODEL,
    Candidate,
    Recommendation,
    RecommendProgress,
    gain_and_uncertainty,
    recommend,
    recommend_calibration,
)

__all__ = ["SearchEnsemble", "ensemble_gain", "load_search_ensemble", "recommend_ensemble", "search"]


@dataclasses.dataclass
class SearchEnsemble:
    """Pose models the rescan search consults together (see the module docstring)."""

    members: list[Any]

    def __post_init__(self) -> None:
        if len(self.members) < 2:
            raise ValueError(f"a search ensemble needs at least 2 model sets, got {len(self.members)}")
        names = [list(m.feature_names) for m in self.members]
        if any(n != names[0] for n in names[1:]):
            raise ValueError("the search ensemble's model sets do not share their feature list")

    @property
    def id(self) -> str:
        """``ensemble:`` and the members' ids joined by ``+`` (the service's ``model_id``)."""
        return "ensemble:" + "+".join(str(m.id) for m in self.members)

    @property
    def feature_names(self) -> list[str]:
        return list(self.members[0].feature_names)


def load_search_ensemble(path: str | Path, primary: Any, threads: int = 1) -> SearchEnsemble:
    """The members in ``path``'s sub-directories that hold a ``card.json`` (sorted by name), each loaded as a pose
    model next to ``primary`` (``inference.load_pose_model``: the primary's features, the same scanner) with a
    well-formed recommender calibration. Raises ValueError / ModelLoadError (the node then searches without it)."""
    from ..judge.inference import load_pose_model

    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"search ensemble directory {str(root)!r} does not exist")
    dirs = sorted(d for d in root.iterdir() if (d / "card.json").is_file())
    members = [load_pose_model(d, primary, threads=threads) for d in dirs]
    for m in members:
        recommend_calibration(m)
    return SearchEnsemble(members)


def _key(c: Candidate) -> tuple[float, ...]:
    s = c.settings
    return (s.lateral_density, s.direction_density, s.exposure_ms, *np.round(np.asarray(c.rotation), 6).ravel())


def _mean_candidate(cs: list[Candidate]) -> Candidate:
    """The members' evaluations of one set-up, as one candidate: their mean figures."""
    def mean(f: str) -> float:
        return float(np.mean([getattr(c, f) for c in cs]))

    pred = [c.predicted_p95_mm for c in cs]
    return dataclasses.replace(
        cs[0], mean_mm=mean("mean_mm"), p95_mm=mean("p95_mm"), coverage=mean("coverage"),
        total_p95_mm=None if any(c.total_p95_mm is None for c in cs) else mean("total_p95_mm"),
        score_unc_mm=float(np.sqrt(np.mean([c.score_unc_mm ** 2 for c in cs]))), u_p95_mm=mean("u_p95_mm"),
        out_of_domain=max(c.out_of_domain for c in cs),
        predicted_p95_mm=None if any(p is None for p in pred) else float(np.mean(pred)))  # type: ignore[arg-type]


def ensemble_gain(gains: np.ndarray, uncs: np.ndarray) -> tuple[float, float]:
    """The ensemble's predicted gain (mm) and its uncertainty from the members' gains and their own uncertainties:
    ``(mean(g), sqrt(mean(u²) + var(g)))``, ``var`` with M − 1 (module docstring)."""
    g, u = np.asarray(gains, np.float64), np.asarray(uncs, np.float64)
    if not np.isfinite(g).all():  # a member's current set-up covers none of the region: any covering one gains
        return math.inf, float(np.sqrt(np.mean(u ** 2)))
    return float(g.mean()), float(np.sqrt(np.mean(u ** 2) + (g.var(ddof=1) if len(g) > 1 else 0.0)))


def recommend_ensemble(ensemble: SearchEnsemble, ctx: Any, rows: np.ndarray, before_features: np.ndarray,
                       pose: Any, scanner: Any, settings: Any, candidates: list[Any] | None = None, *,
                       keep_current: bool = True, rank_by: str = "score", max_seconds: float | None = None,
                       progress: Callable[[RecommendProgress], None] | None = None,
                       prediction_rel_unc: float | str = FROM_MODEL, **kw: Any) -> Recommendation:
    """:func:`recommend.recommend` with every member of ``ensemble`` (see the module docstring); the arguments are
    ``recommend``'s (``max_seconds`` is shared out evenly between the members; ``progress`` counts the members'
    orientations one after another, with the best p95 any member has predicted so far, and its last report is the
    answer's own figure). Raises ValueError when no candidate is evaluated by every member."""
    n = len(ensemble.members)
    runs: list[Recommendation] = []
    ks: list[float] = []
    # Feedback: the members' orientations counted one after another, the best p95 any member has predicted so far;
    # the last member's reports go out one late, so that the very last one is the answer's own figure (as recommend).
    best_so_far, pending = math.inf, None
    for i, m in enumerate(ensemble.members):
        def member_progress(p: RecommendProgress, i: int = i) -> None:
            nonlocal best_so_far, pending
            if progress is None:
                return
            best_so_far = min(best_so_far, p.best_p95_mm)
            q = dataclasses.replace(p, evaluated=p.evaluated + i * p.total, total=p.total * n,
                                    best_p95_mm=best_so_far)
            if i < n - 1:
                progress(q)
                return
            if pending is not None:
                progress(pending)
            pending = q

        runs.append(recommend(m, ctx, rows, before_features, pose, scanner, settings, candidates,
                              keep_current=False, rank_by=rank_by, progress=member_progress,
                              max_seconds=None if max_seconds is None else max_seconds / n,
                              prediction_rel_unc=prediction_rel_unc, **kw))
        ks.append(recommend_calibration(m).prediction_rel_unc if prediction_rel_unc == FROM_MODEL
                  else float(prediction_rel_unc))
    maps = [{_key(c): c for c in r.ranked} for r in runs]
    common = [k for k in maps[0] if all(k in mp for mp in maps[1:])]
    if not common:
        raise ValueError("no candidate lies in the domain of every model of the search ensemble")
    merged = {k: _mean_candidate([mp[k] for mp in maps]) for k in common}

    def key(c: Candidate) -> tuple[float, float]:
        v = c.predicted_p95_mm if rank_by == "predicted" and c.predicted_p95_mm is not None else c.score_mm
        return (v, c.mean_mm)

    ranked = sorted(merged.values(), key=key)
    top = ranked[0]
    tk = _key(top)
    before = _mean_candidate([r.before for r in runs])
    g = np.array([r.before.reported_p95_mm - mp[tk].reported_p95_mm for r, mp in zip(runs, maps, strict=True)])
    u = np.array([gain_and_uncertainty(r.before, mp[tk], k)[1] for r, mp, k in zip(runs, maps, ks, strict=True)])
    gain, gain_unc = ensemble_gain(g, u)
    lead = runs[0]
    note = (f"search ensemble of {n} pose models ({', '.join(str(m.id) for m in ensemble.members)}), "
            f"ranked on their mean; {len(common)} candidates in every model's domain; first model: {lead.note}")
    best, kept = top, False
    um = " / ".join(f"{x * 1e3:.1f}" for x in g)
    if keep_current and not gain > gain_unc:
        cur = [c for c in ranked if c.settings == settings and np.allclose(c.rotation, np.eye(3))]
        best, kept = (cur[0] if cur else before), True
        note += (f"; keep the current set-up: the best candidate's mean predicted gain {gain * 1e3:.1f} um (models: "
                 f"{um} um) does not exceed its uncertainty {gain_unc * 1e3:.1f} um (theirs and their spread)")
    else:
        note += f"; predicted gain {gain * 1e3:.1f} um (models: {um} um), uncertainty {gain_unc * 1e3:.1f} um"
    if progress is not None and pending is not None:
        progress(dataclasses.replace(pending, best_p95_mm=best.reported_p95_mm))
    return dataclasses.replace(
        lead, best=best, before=before, ranked=ranked, note=note, kept_current=kept, top=top,
        n_out_of_domain=sum(r.n_out_of_domain for r in runs) + sum(len(mp) - len(common) for mp in maps),
        n_orientations_evaluated=min(r.n_orientations_evaluated for r in runs),
        n_orientations_kept=min(r.n_orientations_kept for r in runs), gain=(gain, gain_unc))


def search(model_set: Any, ctx: Any, rows: np.ndarray, before_features: np.ndarray, pose: Any, scanner: Any,
           settings: Any, candidates: list[Any] | None = None, **kw: Any) -> Recommendation:
    """The rescan search with ``model_set``: :func:`recommend_ensemble` for a :class:`SearchEnsemble`, else
    :func:`recommend.recommend` (the same arguments)."""
    if isinstance(model_set, SearchEnsemble):
        return recommend_ensemble(model_set, ctx, rows, before_features, pose, scanner, settings, candidates, **kw)
    return recommend(model_set, ctx, rows, before_features, pose, scanner, settings, candidates, **kw)
