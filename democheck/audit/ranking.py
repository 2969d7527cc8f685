"""The ranking: how a table of scores becomes one column, ``suspicion`` -- a pure function of the scores and a
``RankingConfig``, which holds how each score enters (``ScoreSpec``) as data.

Each score in robust standard deviations within the group its demo is judged in (``ranking_z``), a tail
probability fitted on the audited demos' robust core, and those combined (Fisher-Brown, the recording faults
beside the rest, the scores of one look merged -- ``scores`` holds the arithmetic): ``rank``.  The config also
holds which finding leads a reason (``Precedence``), which ``democheck.audit.reasons`` reads.  The registry
(``democheck.audit.scorers``) builds the config from the ranking recipe; this module knows no check by name.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np

from democheck.audit.flagging import conformal_p
from democheck.audit.scores import calibrated, combined_log10, robust_tails


@dataclass(frozen=True)
class ScoreSpec:
    """How one score enters the ranking."""

    name: str
    log: bool = False  # on a log scale first (a squared error's long right tail)
    in_robust_sd: bool = False  # already a robust z within its task: taken as it is
    floor: float = 0.0  # the least spread a robust standard deviation stands for, in the score's units
    tail: str = "exponential"  # the family of its clean right tail: "exponential" or "normal"
    alone: bool = False  # a recording fault: beside the others' sum, by its Sidak minimum
    beside: bool = False  # in the sum, and beside it too: evidence that adds to the rest and is a defect by itself
    look: str = ""  # scores of one look (one piece of evidence) are merged first; "" = its own look
    lead: int = 0  # where its finding stands in a reason's precedence (``Precedence.order``): lower leads


@dataclass(frozen=True)
class Rule:
    """An exception to the precedence's order: where the lead would be ``over`` (each 'check' or 'check:kind')
    and ``first`` is beyond every clean demo too, ``first`` leads -- where every finding of ``when`` is beyond
    too and none of ``unless`` is named in the reason (a rule applies on clear evidence; any evidence against it
    stops it).  ``same_camera``: only over a finding read from the camera ``first`` was read from (a camera that
    stopped explains its own pictures, not another camera's).  ``says_again``: findings that tell the lead's story
    again in part (a reset's start, where it ends): where ``first`` leads, its reason leaves them out."""

    first: str
    over: tuple[str, ...]
    when: tuple[str, ...] = ()
    unless: tuple[str, ...] = ()
    same_camera: bool = False
    says_again: tuple[str, ...] = ()


@dataclass(frozen=True)
class Precedence:
    """Which finding leads a reason, as data (the ranking recipe's ``[reasons]``): the checks in the order a
    reason names them of equally strong evidence (``order``; the others after, recording faults first, the
    model's readings last: ``ScoreSpec.lead``), the kinds that say how a demo differs but not what went wrong
    (``demoted``: they lead only where no other finding is beyond every clean demo), the exceptions (``rules``) and the checks whose
    findings say what the demo did (``behaviour``: where the lead is a reading, one of these leads instead)."""

    order: tuple[str, ...] = ()
    demoted: tuple[str, ...] = ()
    rules: tuple[Rule, ...] = ()
    behaviour: tuple[str, ...] = ()

    @classmethod
    def from_dict(cls, d: Mapping) -> Precedence:
        return cls(**{k: tuple(Rule(**{**r, **{f: tuple(r.get(f, ())) for f in ("over", "when", "unless",
                                                                           "says_again")}})
                               for r in v) if k == "rules" else tuple(v) for k, v in d.items()})


@dataclass(frozen=True)
class RankingConfig:
    """Every ranked score's ``ScoreSpec``, the settings of the combination and the reasons' ``Precedence``, as
    data (``summary.json`` records it; ``benchmarks/ranking`` varies it)."""

    specs: tuple[ScoreSpec, ...]
    # A demo whose combined probability is at most this leaves the robust core: higher leaves clean demos out of
    # the core (and so flagged); lower keeps weakly seen bad demos in, where they take the flags' budget.
    core_p: float
    reason_p: float  # a score this surprising (tail probability) is named in a reason beside the first
    precedence: Precedence = Precedence()
    task_units: bool = False  # a task whose clean demos spread more is judged in its own unit (``calibrated``)

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.specs]

    def looks(self) -> np.ndarray:
        """[K] numbers, equal for the scores of one look."""
        keys = [s.look or s.name for s in self.specs]
        return np.array([keys.index(k) for k in keys], int)

    def without(self, *names: str) -> RankingConfig:
        return replace(self, specs=tuple(s for s in self.specs if s.name not in names))

    def with_spec(self, name: str, **changes) -> RankingConfig:
        return replace(self, specs=tuple(replace(s, **changes) if s.name == name else s for s in self.specs))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping) -> RankingConfig:
        """The config ``to_dict`` wrote; keys a spec no longer has (an older audit's) are left out."""
        keys = {f.name for f in fields(ScoreSpec)}
        return cls(**{**d, "specs": tuple(ScoreSpec(**{k: v for k, v in s.items() if k in keys})
                                          for s in d.get("specs", ())),
                      "precedence": Precedence.from_dict(d.get("precedence", {}))})


@dataclass
class Ranking:
    """``rank``'s result: the ranked scores' tail probabilities (natural logs [N, K], in ``config.names``' order),
    the robust core they were fitted on (bool [N]), and ``suspicion`` = -log10 of the combined probability (+inf
    for a broken recording)."""

    config: RankingConfig
    log_p: np.ndarray
    core: np.ndarray
    suspicion: np.ndarray
    broken: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def per_check(self, fpr: float) -> dict[str, np.ndarray]:
        """``p_<name>``: each ranked score's tail probability, comparable across scores; ``is_<name>``: whether
        that score alone puts the demo among the ``fpr`` most surprising of the core (conformal, as the flag, on
        -log10 of the probability, the suspicion's scale)."""
        out = {}
        for k, name in enumerate(self.config.names):
            lp = self.log_p[:, k]
            out[f"p_{name}"] = np.exp(lp)
            surprise = np.where(np.isnan(lp), -np.inf, -lp / np.log(10.0))
            out[f"is_{name}"] = ~np.isnan(lp) & (conformal_p(surprise, self.core) <= fpr)
        return out


def ranking_z(values: Mapping[str, np.ndarray], groups: np.ndarray, config: RankingConfig,
              core: np.ndarray | None = None) -> np.ndarray:
    """[N, K]: the config's scores in robust standard deviations within the group each demo is judged in (a score
    on a log scale first where its spec says so; one that is a robust z already as it is), each group's centre and
    unit from the ``core`` demos (default: every demo; ``scores.calibrated``)."""
    cols = []
    for s in config.specs:
        x = np.asarray(values[s.name], np.float64)
        x = np.log(np.maximum(x, 1e-12)) if s.log else x
        cols.append(x if s.in_robust_sd else calibrated(x, groups, min_scale=s.floor, core=core,
                                                        task_units=config.task_units))
    return np.column_stack(cols) if cols else np.zeros((len(groups), 0))


def rank(values: Mapping[str, np.ndarray], groups: np.ndarray, config: RankingConfig,
         broken: np.ndarray | None = None) -> Ranking:
    """Rank demos by their scores ``values`` (by name; at least ``config.names``) judged within ``groups``: the
    tails fitted on the robust core (``scores.robust_tails``) and combined.  ``broken`` demos (bool [N]) are never
    in the core and rank first."""
    n = len(groups)
    broken = np.zeros(n, bool) if broken is None else np.asarray(broken, bool)
    if not config.specs:
        return Ranking(config, np.zeros((n, 0)), ~broken, np.full(n, np.nan), broken)
    normal = np.array([s.tail == "normal" for s in config.specs], bool)
    alone = np.array([s.alone for s in config.specs], bool)
    beside = np.array([s.beside for s in config.specs], bool)
    looks = config.looks()
    log_p, core = robust_tails(lambda c: ranking_z(values, groups, config, c), core_p=config.core_p, normal=normal,
                               alone=alone, outside=broken, looks=looks, beside=beside)
    suspicion = -combined_log10(log_p, alone, looks, beside)
    return Ranking(config, log_p, core, np.where(broken, np.inf, suspicion), broken)
