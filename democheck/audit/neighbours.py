"""A demo against its nearest task-mates, in units of their spread: what the time-aligned checks
(``democheck.audit.timeline``) share.  Features are put in robust SD of a group (``in_units``), each demo is compared
with its nearest mates (``nearest``: feature by feature; ``nearest_whole``: whole vectors), and a distance is
ordinary where the group's demos commonly have it (``ordinary``).

How many mates (``mates``): ``NEAR``, or more in a large group, so that a fault up to ``SHARED`` of the group's
demos share -- an operator's resets, recorded one after another -- cannot be its own reference: the median over the
mates is then another demo's.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

NEAR = 5  # task-mates a demo is compared with at least (at most half its group)
SHARED = 0.05  # of a group's demos: a fault this many share still reads as one (``mates``)
MIN_GROUP = 4  # a group of fewer demos gives its demos no score
CLIP = 20.0  # units: a feature further off counts as this far (one wild value is one feature, not the distance)
BLOCK = 256  # demos whose nearest task-mates are found at once (fewer where their differences would pass CELLS)
CELLS = 1 << 24  # differences to the mates held at once (128 MB of float64)
ORDINARY = 3.0  # robust SD: a distance at most this far above its group's usual one is ordinary (``ordinary``)


def units(x: np.ndarray, floor: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Per feature of ``x`` [n, m], the group's median and robust SD (at least ``floor``)."""
    med = np.nanmedian(x, axis=0)
    return med, np.fmax(1.4826 * np.nanmedian(np.abs(x - med), axis=0), floor)


def in_units(x: np.ndarray, unit_of: np.ndarray, floor, pooled: bool = False) -> np.ndarray:
    """``x`` in units of ``unit_of``'s robust SD per feature (``pooled``: their median, one unit for all), clipped
    at ``CLIP``."""
    med, unit = units(unit_of, floor)
    if pooled:
        unit = np.fmax(np.nanmedian(unit), floor)
    return np.clip((x - med) / unit, -CLIP, CLIP)


def mates(others: int) -> int:
    """How many of ``others`` task-mates a demo is compared with: ``NEAR``, or one more than twice ``SHARED`` of
    them (a fault that many share leaves the median over the mates to another demo); at most half of them."""
    return max(1, min(max(NEAR, 2 * int(SHARED * others) + 1), others // 2))


def _near_blocks(query: np.ndarray, ref: np.ndarray, exclude_self: bool
                 ) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """A block of queries at a time (so that memory grows with the group's size, not its square): the block's first
    row, its rows, their squared distances to every ``ref`` row (a query's own row infinite where
    ``exclude_self``) and the ``mates`` nearest of them."""
    k = mates(len(ref) - int(exclude_self))
    rr = (ref * ref).sum(1)
    rows = max(1, min(BLOCK, CELLS // max(1, k * query.shape[1])))
    for a in range(0, len(query), rows):
        b = query[a:a + rows]
        d2 = (b * b).sum(1)[:, None] + rr[None, :] - 2.0 * b @ ref.T
        if exclude_self:
            d2[np.arange(len(b)), np.arange(a, a + len(b))] = np.inf
        yield a, b, d2, np.argpartition(d2, k - 1, axis=1)[:, :k]


def nearest(query: np.ndarray, ref: np.ndarray, exclude_self: bool) -> np.ndarray:
    """[n, m] per demo and feature, the median |query_i - ref_j| over the ``mates`` demos j nearest it (RMS over
    the features), itself left out where ``exclude_self``."""
    q, r = np.nan_to_num(query), np.nan_to_num(ref)
    out = np.empty(q.shape)
    for a, b, _, near in _near_blocks(q, r, exclude_self):
        out[a:a + len(b)] = _median_last(np.abs(b[:, :, None] - r[near].transpose(0, 2, 1)))
    return out


def _median_last(x: np.ndarray) -> np.ndarray:
    """``np.median(x, axis=-1)`` by partition along the contiguous last axis (several times faster with many
    mates)."""
    k = x.shape[-1]
    if k % 2:
        return np.partition(x, k // 2, axis=-1)[..., k // 2]
    part = np.partition(x, [k // 2 - 1, k // 2], axis=-1)
    return (part[..., k // 2 - 1] + part[..., k // 2]) / 2


def nearest_whole(query: np.ndarray, ref: np.ndarray, exclude_self: bool) -> np.ndarray:
    """[n] per demo the mean RMS distance (over the features) to the ``mates`` demos of ``ref`` nearest it (itself
    left out where ``exclude_self``).  Unlike ``nearest``, whole vectors: a few features
    far off (one object's colours beside another's) count however many others agree."""
    dist = np.empty(len(query))
    for a, b, d2, near in _near_blocks(query, ref, exclude_self):
        d2 = np.maximum(np.take_along_axis(d2, near, axis=1), 0.0)
        dist[a:a + len(b)] = np.sqrt(d2 / query.shape[1]).mean(axis=1)
    return dist


def grouped(groups: np.ndarray) -> Iterator[np.ndarray]:
    """The rows of each group of at least ``MIN_GROUP`` demos."""
    for g in np.unique(groups):
        rows = np.flatnonzero(groups == g)
        if len(rows) >= MIN_GROUP:
            yield rows


def rms(diff: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(diff ** 2, axis=1))


def ordinary(x: np.ndarray, usual: np.ndarray, groups: np.ndarray, min_scale: float, log: bool = False
             ) -> np.ndarray:
    """[N] bool: ``x`` at most ``ORDINARY`` robust SD (at least ``min_scale``; of log1p where ``log``) above the
    median of ``usual`` in the demo's group -- a distance its group's demos commonly have."""
    out = np.zeros(len(x), bool)
    f = np.log1p if log else np.asarray
    for rows in grouped(groups):
        ref = f(usual[rows])
        ref = ref[np.isfinite(ref)]
        if len(ref):
            med = np.median(ref)
            out[rows] = f(x[rows]) <= med + ORDINARY * max(1.4826 * np.median(np.abs(ref - med)), min_scale)
    return out
