"""A task's several outcomes, for the ``outcome`` check (``democheck.audit.outcome``): the values a task's demos
leave a feature at split where they fall well apart (``modes``), a pile beside a spread (``piled``), and the
outcomes that follow from where the demos began (``explained``).
"""

from __future__ import annotations

import numpy as np

MODE_SHARE = 0.2  # an outcome this share of a task's demos reach (at least 2) is one of its outcomes,
MODE_GAP = 6.0  # when it lies this many robust SD from the task's other outcomes
PILE_MIN = 10  # demos in a pile: fewer that happen to agree are no pile (see ``modes``)


def modes(r: np.ndarray, floor: float, depth: int = 2, piles: bool = True) -> np.ndarray:
    """[m] which outcome each of a task's values ``r`` (finite) belongs to: the values split at their widest gap
    where both sides hold at least ``MODE_SHARE`` of them (and 2) and the gap is ``MODE_GAP`` times either side's
    robust SD (at least ``floor``) -- twice over at most, so up to four outcomes; one outcome (all 0) otherwise.

    With ``piles``, a pile comes first: where half the values (at least ``PILE_MIN``) lie close together (a part
    against its stop, an object most demos leave where it rests) and the values above it or below it spread
    ``MODE_GAP`` times wider, each such side that holds ``MODE_SHARE`` of them is an outcome of its own -- a
    spread beside a pile is not measured in the pile's spread of almost nothing, while a few failures beside a
    pile of successes stay failures.  A pile is no switch: without ``piles`` only gaps split."""
    m = len(r)
    label = np.zeros(m, int)
    least = max(2, int(np.ceil(MODE_SHARE * m)))
    if depth == 0 or m < 2 * least:
        return label
    if piles:
        label = piled(r, floor)
        if label.any():
            return label
    order = np.argsort(r, kind="stable")
    v = r[order]
    cuts = np.arange(least, m - least + 1)  # the split before position c
    gaps = v[cuts] - v[cuts - 1]
    c = int(cuts[np.argmax(gaps)])
    spread = max(sd(v[:c]), sd(v[c:]), floor)
    if v[c] - v[c - 1] <= MODE_GAP * spread:
        return label
    low, high = order[:c], order[c:]
    label[low] = modes(r[low], floor, depth - 1, piles)
    label[high] = modes(r[high], floor, depth - 1, piles) + label[low].max() + 1
    return label


def piled(r: np.ndarray, floor: float) -> np.ndarray:
    """[m] ``modes``' pile rule alone: 0 for the pile and the values near it, 1 and 2 for a side beside it that
    spreads ``MODE_GAP`` times wider and holds ``MODE_SHARE`` of the values; all 0 where there is no pile."""
    m = len(r)
    label = np.zeros(m, int)
    least = max(2, int(np.ceil(MODE_SHARE * m)))
    half = (m + 1) // 2
    if m < 2 * least or half < PILE_MIN:
        return label
    v = np.sort(r)
    i = int(np.argmin(v[half - 1:] - v[:m - half + 1]))  # the shortest run of half the values
    centre, reach = np.median(v[i:i + half]), MODE_GAP * max(sd(v[i:i + half]), floor)
    for side in (r < centre - reach, r > centre + reach):
        if side.sum() >= least and sd(r[side]) > reach:
            label[side] = label.max() + 1
    return label


def explained(label: np.ndarray, began: np.ndarray, floor: float) -> np.ndarray:
    """``label`` (a task's outcomes) kept where it follows from where its demos began (``began``, the same feature
    at their first step), else 0: an outcome whose demos started ``MODE_GAP`` robust SD (at least ``floor``) away
    from the others' is the task's -- a button that toggles ends on where it began off.  A demo of an outcome that
    does not follow (a fault shared by a few of the task's demos: the other object pushed too; a button never
    pressed) joins the kept outcome whose demos began nearest to where it began, and is measured against those;
    with fewer than two outcomes kept, every demo is of one outcome."""
    kept = []
    if np.isfinite(began).all():
        for k in np.unique(label):
            mine, rest = began[label == k], began[label != k]
            if abs(np.median(mine) - np.median(rest)) > MODE_GAP * max(sd(mine), sd(rest), floor):
                kept.append(k)
    if len(kept) < 2:
        return np.zeros_like(label)
    starts = np.array([np.median(began[label == k]) for k in kept])
    out = np.array(kept)[np.argmin(np.abs(began[:, None] - starts[None, :]), axis=1)]
    return np.where(np.isin(label, kept), label, out)


def several(label: np.ndarray) -> bool:
    """Whether a task's demos reach more than one of ``label``'s outcomes, each held by ``MODE_SHARE`` of them
    (at least 2)."""
    counts = np.unique(label, return_counts=True)[1]
    return int((counts >= max(2, MODE_SHARE * len(label))).sum()) > 1


def sd(v: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(v - np.median(v))))
