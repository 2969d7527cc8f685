"""The ranking: how a table of scores becomes one column, ``suspicion`` -- a pure function of the scores and a
``RankingConfig``, which holds how each score enters (``ScoreSpec``) as data.

Each score in robust standard deviations within the group its demo is judged in (``ranking_z``), a tail
probability fitted on the audited demos' robust core, and those combined (Fisher-Brown, the recording faults
beside the rest, the scores of one look merged -- ``scores`` holds the arithmetic): ``rank``.  ``explain`` turns a
``Ranking`` and the checks' own words into reasons.  The registry (``democheck.audit.scorers``) builds the config
from its scorers (``scorers.ranking_config``); this module knows no check by name.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from democheck.audit.flagging import DEFAULT_FPR, conformal_p
from democheck.audit.scores import calibrated, combined_log10, merge_looks, robust_tails


@dataclass(frozen=True)
class ScoreSpec:
    """How one score enters the ranking."""

    name: str
    log: bool = False  # on a log scale first (a squared error's long right tail)
    in_robust_sd: bool = False  # already a robust z within its task: taken as it is
    floor: float = 0.0  # the least spread a robust standard deviation stands for, in the score's units
    tail: str = "exponential"  # the family of its clean right tail: "exponential" or "normal"
    alone: bool = False  # a recording fault: beside the others' sum, by its Sidak minimum
    look: str = ""  # scores of one look (one piece of evidence) are merged first; "" = its own look
    lead: int = 0  # where its words stand in a reason beyond every clean demo: lower leads
    behaviour: bool = False  # its words say what the demo did (the arm, the world it left, what the camera saw)


@dataclass(frozen=True)
class RankingConfig:
    """Every ranked score's ``ScoreSpec`` and the settings of the combination, as data (``summary.json`` records
    it; ``benchmarks/ranking`` varies it)."""

    specs: tuple[ScoreSpec, ...]
    # A demo whose combined probability is at most this leaves the robust core: higher leaves clean demos out of
    # the core (and so flagged); lower keeps weakly seen bad demos in, where they take the flags' budget.
    core_p: float
    reason_p: float  # a score this surprising (tail probability) is named in a reason beside the first

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
        return cls(**{**d, "specs": tuple(ScoreSpec(**s) for s in d.get("specs", ()))})


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

    def look_odds(self) -> np.ndarray:
        """``log_p`` as a reason reads it: in each row, the score of a look of several that drove it carries the
        look's merged tail probability (what the ranking counted), the look's other scores NaN, so that one look
        is named once, at its own odds."""
        looks = self.config.looks()
        out = np.array(self.log_p, np.float64, copy=True)
        for look in np.unique(looks):
            cols = np.flatnonzero(looks == look)
            if len(cols) < 2:
                continue
            merged, _ = merge_looks(self.log_p[:, cols], np.zeros(len(cols), int))
            first = cols[np.argmin(np.nan_to_num(self.log_p[:, cols], nan=np.inf), axis=1)]
            out[:, cols] = np.nan
            out[np.arange(len(out)), first] = merged[:, 0]
        return out

    def per_check(self, fpr: float) -> dict[str, np.ndarray]:
        """``p_<name>``: each ranked score's tail probability, comparable across scores; ``is_<name>``: whether
        that score alone puts the demo among the ``fpr`` most surprising of the core (conformal, as the flag)."""
        out = {}
        for k, name in enumerate(self.config.names):
            lp = self.log_p[:, k]
            out[f"p_{name}"] = np.exp(lp)
            surprise = np.where(np.isnan(lp), -np.inf, -lp)
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
        cols.append(x if s.in_robust_sd else calibrated(x, groups, min_scale=s.floor, core=core))
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
    looks = config.looks()
    log_p, core = robust_tails(lambda c: ranking_z(values, groups, config, c), core_p=config.core_p, normal=normal,
                               alone=alone, outside=broken, looks=looks)
    suspicion = -combined_log10(log_p, alone, looks)
    return Ranking(config, log_p, core, np.where(broken, np.inf, suspicion), broken)


def beyond_every_clean(log_p: np.ndarray | float, references: int) -> np.ndarray | bool:
    """Whether a tail probability (its natural log) lies beyond what ``references`` demos believed clean can
    support: rarer than one in ``references + 1``."""
    return np.exp(log_p) * (references + 1) < 1


def explain(ranking: Ranking, words: Mapping[str, list[str]], broken_words: list[str] | None = None,
            demoted: Mapping[str, np.ndarray] | None = None,
            yields: Iterable[tuple[str, str, np.ndarray]] = ()) -> tuple[list[str], list[str]]:
    """Each demo's reason and the check it names first: what the checks saw in their own ``words`` (by name, one
    per demo), in the order ``clauses`` gives, each with which check and how rare; a broken recording's
    ``broken_words``.  ``demoted`` (by name, bool per demo): where a check's words say how the demo differs but
    not what went wrong, so that they lead a reason only where nothing else can.  ``yields`` ((check, other, bool
    per demo), the first that holds counts): where a check gives the lead to the other when both are beyond every
    clean demo."""
    names, n = ranking.config.names, len(ranking.suspicion)
    references = int(np.asarray(ranking.core, bool).sum())
    weak = np.column_stack([np.asarray((demoted or {}).get(k, np.zeros(n, bool)), bool) for k in names]
                           ) if names else np.zeros((n, 0), bool)
    after = [(names.index(a), names.index(b), np.asarray(mask, bool)) for a, b, mask in yields
             if a in names and b in names]
    reasons, first = [], []
    for i, row in enumerate(np.nan_to_num(ranking.look_odds(), nan=0.0)):  # no score: nothing to name
        if ranking.broken.size and ranking.broken[i]:
            reasons.append(f"broken: {(broken_words or [''] * n)[i]}")
            first.append("broken")
            continue
        order = clauses(ranking.config, row, references, weak[i], [(a, b) for a, b, mask in after if mask[i]])
        parts = []
        for j in order:  # what the check saw in its own words first, then which check and how rare
            own = (words.get(names[j]) or [""] * n)[i]
            odds = _odds(float(row[j]), references)
            parts.append(f"{own} ({names[j]}, {odds})" if own else f"{names[j]}: {odds}")
        reasons.append("; also ".join(parts))
        first.append(names[order[0]] if order else "")
    return reasons, first


def clauses(config: RankingConfig, row: np.ndarray, references: int, demoted: np.ndarray | None = None,
            yields: list[tuple[int, int]] = ()) -> list[int]:
    """The looks a demo's reason names (``row``: their log tail probabilities), in the order it names them: up to
    three, the smallest probability and those under ``reason_p``.  First, of those beyond every clean demo (or the
    smallest alone), the one whose spec leads (what the demo did before how it was recorded before the model's
    reading of it -- a reviewer acts on the behaviour; a ``demoted`` one only where no other is beyond); where
    that is a reading (neither behaviour nor a recording fault), a behaviour under ``reason_p`` leads instead: by
    its spec's order among those beyond every clean demo, else among those that would flag the demo alone
    (``DEFAULT_FPR``), else the rarest -- a look barely under ``reason_p`` does not lead one that is clearly
    unusual; a look that ``yields`` to another (pairs of columns) where both are beyond gives it the lead.  Then
    by probability."""
    if not len(row):
        return []
    specs = config.specs
    demoted = np.zeros(len(row), bool) if demoted is None else np.asarray(demoted, bool)
    order = [j for j in np.argsort(row, kind="stable") if j == np.argmin(row) or row[j] < np.log(config.reason_p)]
    beyond = [j for j in order if beyond_every_clean(row[j], references)]

    def first(among: list[int]) -> int:
        def key(j: int) -> tuple:
            tier = 0 if j in beyond else 1 if row[j] <= np.log(DEFAULT_FPR) else 2
            return tier, specs[j].lead if tier < 2 else 0, row[j]

        return min([j for j in among if not demoted[j]] or among, key=key)

    lead = first(beyond or order[:1])
    lead = next((b for a, b in yields if a == lead and b in beyond), lead)
    if not (specs[lead].behaviour or specs[lead].alone):  # a reading (the coupling, the model): what the demo did
        plain = [j for j in order if specs[j].behaviour]
        lead = first(plain) if plain else lead
    return [lead, *[j for j in order if j != lead]][:3]


REASON_CHARS = 160  # a reason keeps the driving check's clause and adds the others' while it stays this short


def brief(reason: str) -> str:
    """A reason as the table's ``reason`` holds it: the driving check's clause whole, then the others' while the
    whole stays within ``REASON_CHARS`` (all of them are in ``details``)."""
    parts = str(reason).split("; also ")
    out = parts[0]
    for part in parts[1:]:
        if len(out) + len("; also ") + len(part) > REASON_CHARS:
            break
        out += "; also " + part
    return out


def _odds(log_p: float, references: int) -> str:
    """'as unusual as 1 clean demo in 3,400' for a tail probability (given as its natural log), to two
    significant figures; past what ``references`` demos believed clean can support, 'beyond every clean demo'."""
    p = float(np.exp(log_p))
    if p >= 0.5:
        return "typical"
    if beyond_every_clean(log_p, references):
        return "beyond every clean demo"
    return f"as unusual as 1 clean demo in {float(f'{1 / p:.2g}'):,.0f}"
