"""The time-aligned checks (model-free): a demo's start against its task's starts, its end against their ends, its
path against their paths.

The other checks summarise a demo over time, so a demo done backwards -- a reset recorded as a demo, the object
carried from where it should end to where it should start -- has their numbers: the same frames, colours and joint
values, in the other order.  Compared in time, it begins where its task's demos end and ends where they begin; a
failed place or a knocked-over object shows in the last frames, a detour or a regrasp along the path.

- ``start``: the first ``END_FRAMES`` frames (their median, ``END_THUMB`` px);
- ``end``: the last frames;
- ``path``: ``PATH_POINTS`` evenly spaced points of the demo in normalised time, of its state and of a grey
  ``PATH_THUMB`` px thumbnail;
- ``backwards``: both ends' colour pairs nearer the task's other end (``toward_other_end``, below);
- ``backwards_state`` (``democheck.audit.way``): the state's first value near its task's last, and its last near
  their first, one dimension at a time.

The start and end read the camera alone: where the state ends, and how far it moved, is the outcome check's
(``democheck.audit.outcome``), which knows rotations, piles and a task's several outcomes; read twice, one end state
would count twice.  ``backwards_state`` reads the end states too, but only along the task's way, and stands beside
the others' sum as a recording fault does: whether the recording should be a demo, not where it left the world.

A demo is compared with its nearest task-mates, not with the task's median, so that a task done two ways (the object
placed left or right) has two kinds of clean end; with enough of them (``neighbours.mates``) that a few demos
sharing a fault -- resets recorded one after another -- are not each other's reference.  Each feature is in units
of its robust SD over the group (at least ``VIEW_FLOOR`` grey levels, or ``STATE_FLOOR`` of the dimension's whole
range over the dataset; a path's picture in one unit for all its pixels).  A start's or end's picture is unlike its
mates' by the share of its pixels more than ``UNLIKE`` units from theirs (the median over the mates), as the view
check counts; a path by its ``PATH_DISTANCES``, the largest robust z of its state's and its picture's.  The demo
played backwards gives the words: an end as near its mates' starts as their ends are to each other
(``neighbours.ordinary``), and nearer than to their ends, "ends where its task's demos begin"; a path so near its
mates' played backwards "runs opposite to its task's".

Where each demo lays its objects out anew, or the camera stands elsewhere, pixel by pixel a first picture is as
near its mates' last as their first: a reset's start is then no further from theirs than any.  Which colours lie
beside which (``arrangement``: the object on its plate, or on the table) does not depend on where: a start or an
end is also scored by how much nearer its mates' other end than their same end it lies, at both ends
(``toward_other_end``, the lesser of the start's and the end's: done backwards is backwards at both), the larger
robust z of that and the pixels' counting.

A dataset with no camera has the path's state part alone; one with no state compares its actions instead.
"""

from __future__ import annotations

import cv2
import numpy as np

from democheck.audit import words
from democheck.audit.colours import colour_bins
from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo
from democheck.audit.neighbours import ORDINARY, grouped, in_units, nearest, nearest_whole, ordinary, rms
from democheck.audit.scores import calibrated
from democheck.audit.view import VIEW_FLOOR, VIEW_K, VIEW_MIN_SCALE, place
from democheck.data.demo import Demo

END_FRAMES = 3  # frames at each end whose median picture stands for it (one frame may be a codec's glitch)
END_THUMB = 24  # pixels: the side of the thumbnail of a demo's first and last picture
PATH_POINTS = 32  # points of a demo's path, evenly spaced from its first step to its last
PATH_THUMB = 8  # pixels: the side of the grey thumbnail at each point of the path
ARRANGE_SIZE = 64  # pixels: the side of the first and last picture whose colours side by side are counted
ARRANGE_HUES = 12  # hues of 30 degrees, each saturated or grey, light or dark (``colours.colour_bins``)
ARRANGE_STEP = 2  # pixels apart: two colours this far apart across or down the picture lie side by side
ARRANGE_FLOOR = 1.0  # root-count units: a robust SD stands for at least one more pair of a kind
ARRANGE_MIN_SCALE = 0.05  # log units: the least robust SD of the colour pairs' log distances within a group
ARRANGE_ALIKE = 0.1  # robust SD: two pictures' colour pairs nearer than this are alike (a distance's least value)
UNLIKE = VIEW_K  # units: a pixel this far from each of its nearest task-mates' differs
STATE_FLOOR = 0.05  # a state dimension's least robust SD: this share of its whole range over the demos' paths
STATE_MIN_SCALE = 0.25  # log units: the least robust SD of the state's and path's log distance within a group
# How far a path lies from its mates' is read two ways, and the larger robust z counts: the RMS over the whole path
# (a path unlike throughout) and the RMS at its furthest point (a few points far off: a detour, a drop and regrasp).
PATH_DISTANCES = ("whole", "furthest")


class Timeline(PerDemo):
    """Consumer of decoded demos: each demo's first and last picture (``END_THUMB`` RGB, median of ``END_FRAMES``
    frames) and its colour pairs (``arrangement``, at ``ARRANGE_SIZE`` px), its grey thumbnails and state at
    ``PATH_POINTS`` points, and the state's names (about 13 kB a demo)."""

    fields = ("first_view", "last_view", "first_arranged", "last_arranged", "view_path", "state_path", "names",
              "from_actions")
    first_view: list[np.ndarray | None]
    last_view: list[np.ndarray | None]
    first_arranged: list[np.ndarray | None]
    last_arranged: list[np.ndarray | None]
    view_path: list[np.ndarray | None]
    state_path: list[np.ndarray]
    names: list[list[str] | None]
    from_actions: list[bool]  # no state recorded: the path is the actions'

    def add(self, demo: Demo) -> None:
        frames = demo.frames
        state = np.asarray(demo.state, np.float64).reshape(len(demo.state), -1)
        named = "state_names"
        if not state.shape[1] or not len(state):
            state, named = np.asarray(demo.actions, np.float64).reshape(len(demo.actions), -1), "action_names"
        at = _points(len(state))
        self.state_path.append(state[at].astype(np.float32) if len(at) else np.full((PATH_POINTS, state.shape[1]),
                                                                                    np.nan, np.float32))
        self.names.append(demo.extra.get(named))
        self.from_actions.append(named == "action_names")
        if frames.ndim != 4 or not frames.shape[1] or not len(frames):
            for kept in (self.first_view, self.last_view, self.first_arranged, self.last_arranged, self.view_path):
                kept.append(None)
            return
        self.first_view.append(picture(frames[:END_FRAMES]))
        self.last_view.append(picture(frames[-END_FRAMES:]))
        self.first_arranged.append(arrangement(picture(frames[:END_FRAMES], ARRANGE_SIZE)))
        self.last_arranged.append(arrangement(picture(frames[-END_FRAMES:], ARRANGE_SIZE)))
        size = (PATH_THUMB, PATH_THUMB)
        self.view_path.append(np.stack([
            cv2.resize(cv2.cvtColor(np.ascontiguousarray(frames[i]), cv2.COLOR_RGB2GRAY), size,
                       interpolation=cv2.INTER_AREA) for i in _points(len(frames))]))


def _points(n: int) -> np.ndarray:
    return np.rint(np.linspace(0, n - 1, PATH_POINTS)).astype(int) if n else np.zeros(0, int)


def picture(frames: np.ndarray, side: int = END_THUMB) -> np.ndarray:
    """The median picture of ``frames`` [T, H, W, >=3] at ``side`` x ``side`` px, RGB uint8."""
    size = (side, side)
    small = [cv2.resize(np.ascontiguousarray(f), size, interpolation=cv2.INTER_AREA)[..., :3] for f in frames]
    return np.median(np.stack(small), axis=0).astype(np.uint8)


def arrangement(pic: np.ndarray) -> np.ndarray:
    """How often each two colours lie side by side in a picture (``ARRANGE_STEP`` px apart across or down, two
    different colours of ``colours.colour_bins`` at ``ARRANGE_HUES``): [k (k - 1) / 2] uint16 counts, one per pair.
    Where in the picture does not count, so a layout drawn anew does not move it; what touches what does -- an
    object on its plate or beside it, a part open or shut."""
    k = ARRANGE_HUES * 4
    b = colour_bins(pic.reshape(-1, 3), ARRANGE_HUES).reshape(pic.shape[:2])
    d = ARRANGE_STEP
    x = np.concatenate([b[:, :-d].ravel(), b[:-d, :].ravel()])
    y = np.concatenate([b[:, d:].ravel(), b[d:, :].ravel()])
    apart = x != y
    lo, hi = np.minimum(x[apart], y[apart]), np.maximum(x[apart], y[apart])
    counts = np.bincount(lo * k + hi, minlength=k * k).reshape(k, k)
    return counts[np.triu_indices(k, 1)].astype(np.uint16)


def state_floor(paths: list[np.ndarray]) -> np.ndarray:
    """Per state dimension, the least robust SD: ``STATE_FLOOR`` of its whole range over every demo's path.  Its
    whole range, not a central one: a dimension that moves in a few demos alone (a block that tumbles) is measured
    in units of how far it moves there, not in units of the stillness of the rest."""
    every = np.concatenate([p for p in paths if len(p)]) if paths else np.zeros((0, 0))
    if not every.size:
        return np.ones(every.shape[1] if every.ndim == 2 else 1)
    return np.maximum(STATE_FLOOR * (np.nanmax(every, axis=0) - np.nanmin(every, axis=0)), 1e-9)


def dimension_names(names: list[str] | None, dims: np.ndarray, source: str) -> str:
    """The dimensions ``dims`` by the names the dataset records, else as "<source>[i]", joined by commas."""
    said = [names[d] if names and d < len(names) else f"{source}[{d}]" for d in dims]
    return ", ".join(said)


def _view_words(which: str, share: float, place: str, **_) -> str:
    return f"{words.percent(share)} of its {which} picture differs from its nearest task-mates' (mostly {place})"


START = Vocabulary("start", {
    # its start nearer its task-mates' ends than their starts
    "where they end": "begins where its task's demos end: done backwards (a reset recorded as a demo?)",
    # by its colour pairs nearer its task-mates' ends than they are, not as near as their own ends are
    "toward the other end": "begins nearer where its task's demos end than they do, by which colours lie beside which",
    "view": lambda **p: "begins unlike its task's demos: " + _view_words("first", **p),
    "like": "begins like its task's demos",
    "no frames": "no camera to compare",
})

END = Vocabulary("end", {
    # its end nearer its task-mates' starts than their ends
    "where they begin": "ends where its task's demos begin: done backwards (a reset recorded as a demo?)",
    "toward the other end": "ends nearer where its task's demos begin than they do, by which colours lie beside which",
    "view": lambda **p: "ends unlike its task's demos: " + _view_words("last", **p),
    "like": "ends like its task's demos",
    "no frames": "no camera to compare",
})


BACKWARDS = Vocabulary("backwards", {
    # both its ends nearer its task-mates' other end than their same end, and as near as their ends are to each other
    "done backwards": "begins where its task's demos end and ends where they begin: done backwards (a reset recorded "
                      "as a demo?)",
    # both ends nearer the mates' other end than the task's demos are, not as near as those are to each other
    "toward the other end": "its first picture lies nearer its task's last pictures, and its last nearer their first, "
                            "than its task's demos do: partly done backwards?",
    "forwards": "goes the way its task's demos go",
    "too few demos": "no task of enough demos to compare with",
    "no frames": "no camera to compare",
})


def _backwards_words(part: str, **_) -> str:
    what = "its state" if part == "state" else "what its camera sees"
    return f"its path runs opposite to its task's: {what}, played backwards, is nearer its task's demos than forwards"


PATH = Vocabulary("path", {
    "backwards": _backwards_words,  # nearer its task-mates' paths played backwards than forwards
    "view": lambda at, **_: f"what its camera sees on the way differs from its task's demos, most {at:.0%} of the "
                            "way through",
    "state": lambda dims, at, **_: f"its path strays from its task's, most in {dims}, {at:.0%} of the way through",
    "like": "its path is like its task's demos'",
})


def _view_part(query: list, groups: np.ndarray, cross: list | None = None
               ) -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    """Per demo, the share of its picture's pixels unlike its nearest task-mates' (``UNLIKE``), that share's
    robust z within its group, the unlike mask [h, w], and the share against ``cross`` (the mates' other end)."""
    n = len(query)
    share, cross_share, masks = np.full(n, np.nan), np.full(n, np.nan), [None] * n
    if any(q is None for q in query):
        return share, np.full(n, np.nan), masks, cross_share
    for rows in grouped(groups):
        q = np.stack([query[i] for i in rows]).astype(np.float64)
        shape = q.shape[1:]
        q = q.reshape(len(rows), -1)
        z = in_units(q, q, VIEW_FLOOR)
        diff = nearest(z, z, exclude_self=True).reshape(len(rows), *shape)
        unlike = (diff > UNLIKE).max(axis=-1)
        share[rows] = unlike.mean(axis=(1, 2))
        for k, i in enumerate(rows):
            masks[i] = unlike[k]
        if cross is not None:
            c = np.stack([cross[i] for i in rows]).astype(np.float64).reshape(len(rows), -1)
            cz = in_units(c, q, VIEW_FLOOR)
            d = nearest(z, cz, exclude_self=True).reshape(len(rows), *shape)
            cross_share[rows] = (d > UNLIKE).max(axis=-1).mean(axis=(1, 2))
    return share, calibrated(share, groups, min_scale=VIEW_MIN_SCALE), masks, cross_share


def _arranged_part(query: list, groups: np.ndarray, cross: list) -> tuple[np.ndarray, np.ndarray]:
    """Per demo, the RMS distance of its picture's colour pairs (``arrangement``: root counts in their group's
    robust SD, at least ``ARRANGE_FLOOR``, over the pairs some picture of the group shows) to its nearest
    task-mates', and to ``cross`` (the mates' other end); NaN without a camera."""
    n = len(query)
    own, cross_dist = np.full(n, np.nan), np.full(n, np.nan)
    if any(q is None for q in query):
        return own, cross_dist
    for rows in grouped(groups):
        q = np.sqrt(np.stack([query[i] for i in rows]).astype(np.float64))
        c = np.sqrt(np.stack([cross[i] for i in rows]).astype(np.float64))
        shown = np.flatnonzero((q > 0).any(axis=0) | (c > 0).any(axis=0))
        z = in_units(q[:, shown], q[:, shown], ARRANGE_FLOOR)
        own[rows] = nearest_whole(z, z, exclude_self=True)
        cross_dist[rows] = nearest_whole(z, in_units(c[:, shown], q[:, shown], ARRANGE_FLOOR), exclude_self=True)
    return own, cross_dist


def toward_other_end(own: np.ndarray, cross: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """[N] robust z within its group of how much nearer a demo's picture lies to its mates' other end than to
    their same end (the log of ``own`` / ``cross``, each at least ``ARRANGE_ALIKE``): a reset's first picture
    is its task's last.  Where the colour pairs do not tell a task's starts from its ends, every demo is about
    as near both and none is far out."""
    ratio = np.log(np.maximum(own, ARRANGE_ALIKE) / np.maximum(cross, ARRANGE_ALIKE))
    return calibrated(ratio, groups, min_scale=ARRANGE_MIN_SCALE)


def _state_part(query: np.ndarray, groups: np.ndarray, floor: np.ndarray | float, backwards: bool = False,
                pooled: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per demo of a path's part (``query`` [N, PATH_POINTS, ...], any dtype), the RMS distance to its nearest
    task-mates over the whole path (in units; ``pooled``: one unit for every feature, as for a picture's pixels,
    where a still background's tiny spread would make any shadow far); the larger robust z within its group, on a
    log scale, of its ``PATH_DISTANCES``; where it is furthest, as the mean distance at each point [N, PATH_POINTS]
    and in each feature of a point [N, m]; and, with ``backwards``, the whole path's RMS distance against the
    mates' paths played backwards.  One group's paths in float64 at a time: memory grows with the largest group."""
    n = len(query)
    m = int(np.prod(query.shape[2:]))
    dist = {name: np.full(n, np.nan) for name in ("whole", "furthest")}
    cross_dist, at_point, in_feature = np.full(n, np.nan), np.full((n, PATH_POINTS), np.nan), np.full((n, m), np.nan)
    for rows in grouped(groups):
        x = np.asarray(query[rows], np.float64)
        flat = x.reshape(len(rows), -1)
        z = in_units(flat, flat, floor, pooled)
        diff = nearest(z, z, exclude_self=True)
        dist["whole"][rows] = rms(diff)
        points = diff.reshape(len(rows), PATH_POINTS, -1)
        dist["furthest"][rows] = rms(points.transpose(0, 2, 1)).max(axis=1)
        filled = np.nan_to_num(points)
        at_point[rows], in_feature[rows] = filled.mean(axis=2), filled.mean(axis=1)
        del diff, points, filled
        if backwards:
            cz = in_units(x[:, ::-1].reshape(len(rows), -1), flat, floor, pooled)
            cross_dist[rows] = rms(nearest(z, cz, exclude_self=True))
    score = np.full(n, np.nan)
    for name in PATH_DISTANCES:
        score = np.fmax(score, calibrated(np.log1p(dist[name]), groups, min_scale=STATE_MIN_SCALE))
    return dist["whole"], score, at_point, in_feature, cross_dist


def stacked_states(paths: list[np.ndarray], at: int | slice) -> np.ndarray:
    width = max((p.shape[1] for p in paths), default=0)
    out = np.full((len(paths), PATH_POINTS, width), np.nan)
    for i, p in enumerate(paths):
        out[i, :len(p), :p.shape[1]] = p
    return out[:, at]


def _compared_ends(t: Timeline, groups: np.ndarray) -> dict:
    """Each end's picture against its mates' same end and other end, pixel by pixel (``_view_part``) and by its
    colour pairs (``_arranged_part``, and whether that end ``crossed`` over to the other), and the colour pairs'
    nearness to the other end at both ends (``toward``): what the start, end and backwards checks read, computed
    once for ``groups`` (kept on ``t``)."""
    key = np.asarray(groups).tobytes()
    kept = getattr(t, "_compared", None)
    if kept is not None and kept[0] == key:
        return kept[1]
    views = {"first": t.first_view, "last": t.last_view}
    arranged = {"first": t.first_arranged, "last": t.last_arranged}
    out = {}
    for which, other in (("first", "last"), ("last", "first")):
        out[which] = {"view": _view_part(views[which], groups, views[other]),
                      "arranged": _arranged_part(arranged[which], groups, arranged[other])}
    for which, other in (("first", "last"), ("last", "first")):
        # by its colour pairs nearer its mates' other end than their same end, and as near as their own ends are to
        # each other: that end crossed over
        own, cross = out[which]["arranged"]
        out[which]["crossed"] = (cross < own) & ordinary(cross, out[other]["arranged"][0], groups, ARRANGE_MIN_SCALE,
                                                          log=True)
    # Done backwards is backwards at both ends: the lesser of the two ends' nearness to the other (a card over the
    # view at one end takes that end's picture away from its mates' same end, and nearer none).
    out["toward"] = np.minimum(*(toward_other_end(*out[which]["arranged"], groups) for which in ("first", "last")))
    t._compared = (key, out)
    return out


def _end(t: Timeline, groups: np.ndarray, which: str) -> tuple[np.ndarray, list[Finding]]:
    """The ``start`` (``which`` "first") or ``end`` ("last") check: see the module docstring."""
    first = which == "first"
    vocab, crossed = (START, "where they end") if first else (END, "where they begin")
    views = t.first_view if first else t.last_view
    if any(v is None for v in views):
        return np.full(len(views), np.nan), [vocab("no frames")] * len(views)
    ends = _compared_ends(t, groups)
    mine, other = ends[which], ends["last" if first else "first"]
    share, view_z, masks, cross = mine["view"]
    own, arranged_cross = mine["arranged"]
    toward = ends["toward"]
    # near its mates' other end, as near as their own other ends are to each other: done backwards
    like_other = ordinary(cross, other["view"][0], groups, VIEW_MIN_SCALE)
    score = np.fmax(view_z, toward)
    found = []
    for i in range(len(score)):
        by_colours = np.isfinite(toward[i]) and not view_z[i] >= toward[i]
        if not np.isfinite(score[i]):
            found.append(vocab("like"))
        elif by_colours and toward[i] > ORDINARY and mine["crossed"][i]:
            found.append(vocab(crossed, distance=float(own[i]), cross=float(arranged_cross[i])))
        elif by_colours and toward[i] > 1.0:  # the colour pairs gave the score, a robust SD or more: say so
            found.append(vocab("toward the other end", z=float(toward[i])))
        elif not share[i]:
            found.append(vocab("like"))
        elif cross[i] < share[i] and like_other[i]:
            found.append(vocab(crossed, share=float(share[i]), cross=float(cross[i])))
        else:
            found.append(vocab("view", share=float(share[i]), place=place(masks[i])))
    return score, found


def backwards(t: Timeline, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How much nearer its task-mates' other end than their same end a demo's first and last pictures lie, by which
    colours lie beside which (``toward_other_end``, the lesser of its two ends, robust z within its task): a reset
    recorded as a demo, the object carried from where the task's demos leave it to where they find it.  Its own
    check beside the start's and the end's, which read it too: a recording that should not be a demo is a defect
    whatever else the demo did, and as one of the three looks in time it would be diluted by their pixels."""
    n = len(t.first_view)
    if any(v is None for v in t.first_view):
        return np.full(n, np.nan), [BACKWARDS("no frames")] * n
    ends = _compared_ends(t, groups)
    toward = ends["toward"]
    crossed = ends["first"]["crossed"] & ends["last"]["crossed"]
    found = []
    for i in range(n):
        if not np.isfinite(toward[i]):
            found.append(BACKWARDS("too few demos"))
            continue
        if not toward[i] > ORDINARY:
            found.append(BACKWARDS("forwards"))
            continue
        params = {"z": float(toward[i])}
        found.append(BACKWARDS("done backwards" if crossed[i] else "toward the other end", **params))
    return toward, found


def start(t: Timeline, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How unlike its task-mates' first picture and state a demo's are (robust z; see the module docstring)."""
    return _end(t, groups, "first")


def end(t: Timeline, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How unlike its task-mates' last picture and state a demo's are (robust z; see the module docstring)."""
    return _end(t, groups, "last")


def path(t: Timeline, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How far a demo's path in normalised time (its state's and its camera's) lies from its nearest task-mates'
    (robust z of the log RMS distance, the larger part's), and whether it runs backwards."""
    n = len(t.state_path)
    parts = {"state": (stacked_states(t.state_path, slice(None)), np.tile(state_floor(t.state_path), PATH_POINTS))}
    if all(v is not None for v in t.view_path):
        parts["view"] = (np.stack(t.view_path), VIEW_FLOOR)  # as kept (uint8): a group at a time in float64
    z, own, reversed_, at_point, in_feature = {}, {}, {}, {}, {}
    for name, (x, fl) in parts.items():
        own[name], z[name], at_point[name], in_feature[name], reversed_[name] = _state_part(
            x, groups, fl, backwards=True, pooled=name == "view")
    # nearer its mates' paths played backwards than forwards, and as near as their paths are to each other
    near_enough = {name: ordinary(reversed_[name], own[name], groups, STATE_MIN_SCALE, True) for name in z}
    score = np.full(n, np.nan)
    for name in z:
        score = np.fmax(score, z[name])
    found = []
    for i in range(n):
        if not np.isfinite(score[i]):
            found.append(PATH("like"))
            continue
        name = max(z, key=lambda p: z[p][i] if np.isfinite(z[p][i]) else -np.inf)
        if reversed_[name][i] < own[name][i] and near_enough[name][i]:
            found.append(PATH("backwards", part="state" if name == "state" else "picture", own=float(own[name][i]),
                              backwards=float(reversed_[name][i])))
            continue
        at = float(np.argmax(np.nan_to_num(at_point[name][i])) / (PATH_POINTS - 1))
        if name == "view":
            found.append(PATH("view", at=at, distance=float(own[name][i])))
        else:
            dims = np.argsort(-np.nan_to_num(in_feature[name][i]))[:2]
            found.append(PATH("state", dims=dimension_names(t.names[i], dims, "state"), at=at,
                              distance=float(own[name][i])))
    return score, found

