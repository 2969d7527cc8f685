"""Reasons: why a demo ranks where it does, in words, from the checks' findings -- one pure function, ``explain``,
of the ranking, the findings and ``--fpr``.  This is the only place that picks the lead, orders the clauses and
words the odds.

Which finding leads is the ranking recipe's declared precedence (``ranking.Precedence``): of the checks on which
the demo is beyond every clean demo (``tiers``: no reference demo as unusual, and a tail rarer than the reference
can support), the first in the recipe's order, a demoted kind only where no other is, an exception of the recipe
where it applies; where that is a reading of the demo (the model's, the coupling's), the behaviour the reading
follows from.  Every clause then says what the check found, which check, and how unusual the demo is on it,
counted against the reference demos (``odds``): "beyond every clean demo" only where the count says so.  The
reference the words count against is the clean demos as the user is told: the robust core the tails were fitted
on, less the demos the audit flags at ``--fpr`` (a bad demo only weakly seen can stay in the core, and one
failed place there would make every other "as unusual as a clean demo").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from democheck.audit.findings import Finding, camera_of, check_of
from democheck.audit.flagging import conformal_p, flags
from democheck.audit.ranking import Ranking, RankingConfig
from democheck.audit.scores import merge_looks

REASON_CHARS = 160  # a reason keeps the lead's clause and adds the others' while it stays this short
CLAUSES = 3  # a reason names at most this many checks


@dataclass(frozen=True)
class Explained:
    """Each demo's reason (every clause, ``details``), its check and finding named first (``driven_by``,
    ``lead``: 'check:kind')."""

    details: list[str]
    driven_by: list[str]
    lead: list[str]


def rare(log_p: np.ndarray, references: int) -> np.ndarray:
    """Whether a tail probability (natural log) is rarer than the reference of ``references`` demos believed clean
    can support, one in ``references + 1``."""
    return np.exp(log_p) * (references + 1) < 1


def look_columns(ranking: Ranking) -> tuple[np.ndarray, np.ndarray]:
    """``ranking.log_p`` [N, K] as a reason reads it, twice: with every score of a look of several
    (``RankingConfig.looks``) carrying the look's merged tail probability (what the ranking counted), and with
    only the score that drove the look in each row carrying it, the look's others NaN (so a reason names a look
    once, by that score)."""
    looks = ranking.config.looks()
    every = np.array(ranking.log_p, np.float64, copy=True)
    shown = every.copy()
    for look in np.unique(looks):
        cols = np.flatnonzero(looks == look)
        if len(cols) < 2:
            continue
        merged, _ = merge_looks(ranking.log_p[:, cols], np.zeros(len(cols), int))
        first = cols[np.argmin(np.nan_to_num(ranking.log_p[:, cols], nan=np.inf), axis=1)]
        every[:, cols] = merged[:, :1]
        shown[:, cols] = np.nan
        shown[np.arange(len(shown)), first] = merged[:, 0]
    return every, shown


def counts(log_p: np.ndarray, core: np.ndarray) -> tuple[np.ndarray, int]:
    """Per demo and column ([N, K]): how many reference demos (the ``core``, the demo itself left out) are at
    least as unusual on that column -- its tail probability, which each check's value became within the demo's
    comparison group, so that demos of every task compare -- and how many reference demos there are.  NaN
    counts as not unusual."""
    core = np.asarray(core, bool)
    x = np.nan_to_num(np.asarray(log_p, np.float64), nan=0.0)
    refs = np.sort(x[core], axis=0)  # ascending: the most unusual first
    at_least = np.column_stack([np.searchsorted(refs[:, j], x[:, j], side="right") for j in range(x.shape[1])]
                               ) if x.shape[1] else np.zeros((len(x), 0), int)
    at_least[core] -= 1  # a reference demo is not compared with itself
    return at_least, int(core.sum())


def tiers(log_p: np.ndarray, at_least: np.ndarray, references: int, core: np.ndarray, fpr: float) -> np.ndarray:
    """[N, K] how strong each look's evidence is, by the count and by the fitted tail (``log_p``) alike: 0 where no
    reference demo is as unusual, the demo is none of them, and its tail probability is rarer than the reference
    can support (``rare``) -- beyond every clean demo --; 1 where both its share of the reference at least as
    unusual and its tail probability are at most ``fpr`` (the look alone would flag it); 2 otherwise."""
    share = (at_least + 1) / (references + 1)
    p = np.nan_to_num(log_p, nan=0.0)
    beyond = (at_least == 0) & ~np.asarray(core, bool)[:, None] & (references > 0) & rare(p, references)
    return np.where(beyond, 0, np.where((share <= fpr) & (p <= np.log(fpr)), 1, 2))


def clean_reference(ranking: Ranking, fpr: float, regardless: np.ndarray) -> np.ndarray:
    """[N] bool: the demos a reason counts as clean -- the ranking's robust core less those the audit flags at
    ``fpr`` (``flagging.flags`` of the core's conformal p-values, or ``regardless``), as ``score_table`` flags
    them."""
    core = np.asarray(ranking.core, bool)
    flagged = flags(conformal_p(np.asarray(ranking.suspicion, np.float64), core), fpr, regardless)
    return core & ~flagged


def odds(at_least: int, references: int, reference: bool) -> str:
    """How unusual a demo is on one check, counted against the ``references`` demos believed clean: 'beyond every
    clean demo' where none is as unusual and the demo is not one of them (``reference``), else 'as unusual as 1
    clean demo in N' (N = (clean demos + 1) / (those at least as unusual + 1), to two figures, the demo itself
    among them where it is one), 'typical' from one in two."""
    of = references - reference
    if at_least == 0 and of > 0 and not reference:
        return "beyond every clean demo"
    n = (of + 1) / (at_least + 1)
    return "typical" if n <= 2 else f"as unusual as 1 clean demo in {float(f'{n:.2g}'):,.0f}"


def _matches(finding: Finding | None, name: str, column: str) -> bool:
    """Whether the finding in ``column`` (a check's, on any camera) is what ``name`` ('check' or 'check:kind')
    names."""
    want, _, kind = name.partition(":")
    return want == check_of(column) and (not kind or (finding is not None and finding.kind == kind))


def lead_of(config: RankingConfig, row: np.ndarray, found: list[Finding | None], tier: np.ndarray) -> list[int]:
    """The looks a demo's reason names (``row``: each column's log tail probability, NaN where a look of several
    is named by another column), in the order it names them: up to ``CLAUSES``, the smallest probability and
    those under ``reason_p``; first the lead the recipe's precedence picks (see the module docstring), then by
    probability.  ``found``: each column's finding for this demo; ``tier``: each column's evidence, 0 beyond every
    clean demo, 1 unusual enough to flag the demo alone, 2 less (``tiers``)."""
    row = np.nan_to_num(row, nan=0.0)
    if not len(row):
        return []
    specs, pre = config.specs, config.precedence
    names = config.names
    order = [j for j in np.argsort(row, kind="stable") if j == np.argmin(row) or row[j] < np.log(config.reason_p)]
    beyond = [j for j in order if tier[j] == 0]
    demoted = [any(_matches(found[j], d, names[j]) for d in pre.demoted) for j in range(len(row))]

    def first(among: list[int]) -> int:
        def key(j: int) -> tuple:
            return tier[j], specs[j].lead if tier[j] < 2 else 0, row[j]

        return min([j for j in among if not demoted[j]] or among, key=key)

    def holds(name: str, among: list[int]) -> bool:
        return any(_matches(found[j], name, names[j]) for j in among)

    lead = first(beyond or order[:1])
    for rule in pre.rules:  # a rule applies on rare evidence, and any evidence named stops it
        if not any(_matches(found[lead], o, names[lead]) for o in rule.over):
            continue
        if not all(holds(c, beyond) for c in rule.when) or any(holds(c, order) for c in rule.unless):
            continue
        other = next((j for j in beyond if _matches(found[j], rule.first, names[j])
                      and (not rule.same_camera or camera_of(names[j]) == camera_of(names[lead]))), None)
        if other is not None:
            lead = other
            break
    if check_of(names[lead]) not in pre.behaviour and not specs[lead].alone:  # a reading: what the demo did leads
        plain = [j for j in order if check_of(names[j]) in pre.behaviour]
        lead = first(plain) if plain else lead
    again = [a for rule in pre.rules if _matches(found[lead], rule.first, names[lead]) for a in rule.says_again]
    rest = [j for j in order if j != lead and not any(_matches(found[j], a, names[j]) for a in again)]
    return [lead, *rest][:CLAUSES]


def explain(ranking: Ranking, findings: Mapping[str, list[Finding]], fpr: float, broken: np.ndarray | None = None,
            copies: np.ndarray | None = None) -> Explained:
    """Every demo's reason: a ``broken`` recording's (bool [N]) the broken check's words, an exact copy's
    (``copies``) the duplicate check's, else the clauses ``lead_of`` picks at ``fpr``, each "<what the check
    found> (<check>, <odds>)" with the odds counted against the reference demos (``counts``, ``odds``)."""
    names, n = ranking.config.names, len(ranking.suspicion)
    broken = np.zeros(n, bool) if broken is None else np.asarray(broken, bool)
    copies = np.zeros(n, bool) if copies is None else np.asarray(copies, bool)
    every, shown = look_columns(ranking)
    clean = clean_reference(ranking, fpr, broken | copies)
    at_least, references = counts(every, clean)
    tier = tiers(every, at_least, references, clean, fpr)
    details, driven, leads = [], [], []
    for i in range(n):
        special = "broken" if broken[i] else "duplicate" if copies[i] else ""
        if special:
            f = findings[special][i]
            details.append(f"broken: {f.words}" if special == "broken" else f.words)
            driven.append(special)
            leads.append(f.key)
            continue
        found = [(findings.get(name) or [None] * n)[i] for name in names]
        picked = lead_of(ranking.config, shown[i], found, tier[i])
        parts = []
        for j in picked:  # what the check saw in its own words first, then which check and how unusual
            words = found[j].words if found[j] is not None else ""
            rate = odds(int(at_least[i, j]), references, bool(clean[i]))
            parts.append(f"{words} ({names[j]}, {rate})" if words else f"{names[j]}: {rate}")
        details.append("; also ".join(parts))
        driven.append(names[picked[0]] if picked else "")
        leads.append(found[picked[0]].key if picked and found[picked[0]] is not None else driven[-1])
    return Explained(details, driven, leads)


def brief(reason: str) -> str:
    """A reason as the table's ``reason`` holds it: the lead's clause whole, then the others' while the whole
    stays within ``REASON_CHARS`` (all of them are in ``details``)."""
    parts = str(reason).split("; also ")
    out = parts[0]
    for part in parts[1:]:
        if len(out) + len("; also ") + len(part) > REASON_CHARS:
            break
        out += "; also " + part
    return out


def precedence_table(config: RankingConfig, kinds: Mapping[str, tuple[str, ...]]) -> str:
    """The precedence a config declares, as ``docs/columns.md`` shows it (markdown): the order, the demoted kinds,
    the rules, and each check's ``kinds`` (by check, its vocabulary)."""
    pre = config.precedence
    lines = ["| | |", "|---|---|",
             f"| order | {', '.join(pre.order)}; then the other recording faults, the other model-free checks, the "
             "model's readings |",
             f"| demoted (lead only where nothing else is beyond) | {', '.join(pre.demoted)} |",
             f"| what the demo did (lead over a reading) | {', '.join(pre.behaviour)} |"]
    for rule in pre.rules:
        when = f"; when {', '.join(rule.when)} is beyond too" if rule.when else ""
        unless = f"; unless {', '.join(rule.unless)} is named" if rule.unless else ""
        same = " on its own camera" if rule.same_camera else ""
        again = f"; its reason leaves out {', '.join(rule.says_again)}" if rule.says_again else ""
        lines.append(f"| rule | {rule.first} leads over {', '.join(rule.over)}{same}{when}{unless}{again} |")
    lines += ["", "| check | kinds |", "|---|---|"]
    lines += [f"| `{check}` | {', '.join(found)} |" for check, found in kinds.items()]
    return "\n".join(lines) + "\n"
