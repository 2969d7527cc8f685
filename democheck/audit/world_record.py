"""What the outcome check compares of a world record: its dimensions grouped into features, by their names and
values -- a quaternion (four dimensions named ``*w/x/y/z`` or ``*quat*``, or, unnamed, of unit norm wherever
recorded), a body's roll, pitch and yaw, another angle, a plain value, and where two things named on one axis are
against each other -- and each feature's values as compared (``represent``): a rotation as ``q q^T`` (the same for
``q`` and ``-q``; roll, pitch and yaw through their quaternion, so the record's form does not change the score), an
angle as its cosine and sine (+pi and -pi are one angle).  ``democheck.audit.outcome`` measures them against each
task's demos."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

_QUAT = re.compile(r"^(.*?)[._/\-]?(?:q|quat|quaternion|orientation|rot)?[._/\-]?\[?([wxyz0-3])\]?$", re.I)
_AXIS = re.compile(r"^(.+?)[._/\-]?(?:pos)?[._/\-]([xyz])$", re.I)
_ANGLE = re.compile(r"(yaw|pitch|roll|angle|theta|heading)", re.I)
_EULER = re.compile(r"^(.*?)[._/\-]?(roll|pitch|yaw)$", re.I)


@dataclass
class Feature:
    """One compared feature of the world record: its name, the columns of the record it reads, its kind
    (``value``, ``rotation`` or ``angle``)."""

    name: str
    columns: list[int]
    kind: str


def features_of(names: list[str] | None, first: np.ndarray, last: np.ndarray, source: str = "state"
                ) -> list[Feature]:
    """The record's dimensions grouped into what is compared: quaternions (by their names or, unnamed, by unit
    norm at both ends of every demo that records them, ``_is_quaternion``), a body's roll, pitch and yaw, angles
    (by their names), plain values, and where two things named on one axis are against each other
    (``block.x - goal.x``)."""
    d = first.shape[1]
    names = list(names) if names and len(names) == d else [f"{source}[{j}]" for j in range(d)]
    euler = _euler_triples(names)
    out, j = [], 0
    while j < d:
        if j in euler:
            if euler[j][0] == j:  # one feature, where its first angle is
                prefix = _EULER.match(names[j]).group(1) or f"{source}[{j}]"
                out.append(Feature(f"the orientation of {prefix}", euler[j], "rotation"))
            j += 1
            continue
        if j + 4 <= d and _is_quaternion(names[j:j + 4], first[:, j:j + 4], last[:, j:j + 4]):
            prefix = _QUAT.match(names[j]).group(1) if _QUAT.match(names[j]) else ""
            out.append(Feature(f"the orientation of {prefix or f'{source}[{j}:{j + 4}]'}",
                               list(range(j, j + 4)), "rotation"))
            j += 4
            continue
        out.append(Feature(names[j], [j], "angle" if _ANGLE.search(names[j]) else "value"))
        j += 1
    # Where two things' positions are named on the same axis (block.x, goal.x), where one is against the other.
    axes: dict[str, dict[str, int]] = {}
    for f in out:
        m = _AXIS.match(f.name) if f.kind == "value" else None
        if m:
            axes.setdefault(m.group(2).lower(), {}).setdefault(m.group(1), f.columns[0])
    for axis, things in axes.items():
        names_on = list(things)
        for a in range(len(names_on)):
            for b in range(a + 1, len(names_on)):
                out.append(Feature(f"{names_on[a]}.{axis} - {names_on[b]}.{axis}",
                                   [things[names_on[a]], things[names_on[b]]], "relative"))
    return out


def _euler_triples(names: list[str]) -> dict[int, list[int]]:
    """The columns of a body's roll, pitch and yaw named so with one prefix (``block.roll``, ``block.pitch``,
    ``block.yaw``), each mapped to the triple's columns in that order: one orientation, compared as a rotation --
    as three angles, a block that rests on another face reads as a roll no demo of its task has, where the same
    turn recorded as a quaternion is one rotation among its task's."""
    bodies: dict[str, dict[str, int]] = {}
    for j, n in enumerate(names):
        m = _EULER.match(n)
        if m:
            bodies.setdefault(m.group(1).lower(), {}).setdefault(m.group(2).lower(), j)
    out = {}
    for axes in bodies.values():
        if len(axes) == 3:
            cols = [axes["roll"], axes["pitch"], axes["yaw"]]
            out.update({c: cols for c in cols})
    return out


def _is_quaternion(names: list[str], first: np.ndarray, last: np.ndarray) -> bool:
    matches = [_QUAT.match(n) for n in names]
    if all(m and m.group(2) for m in matches) and len({m.group(1) for m in matches}) == 1:
        letters = "".join(m.group(2).lower() for m in matches)
        if sorted(letters) in (sorted("wxyz"), sorted("0123")) and re.search(r"q|quat|orient|rot", names[0], re.I):
            return True
    # Unnamed: of unit norm at both ends of every demo that fills it (a task whose record has no such body leaves
    # the slot at zero, as Meta-World's second object and its drawers' and windows' orientation), and turning.
    with np.errstate(all="ignore"):
        norms = np.concatenate([np.linalg.norm(first, axis=1), np.linalg.norm(last, axis=1)])
    filled = norms != 0
    return bool(filled.any() and np.isfinite(norms).all() and np.abs(norms[filled] - 1).max() < 1e-3
                and np.ptp(np.concatenate([first, last])[filled], 0).max() > 1e-3)


def represent(feature: Feature, x: np.ndarray) -> np.ndarray:
    """[N, m] the feature's values as compared: a quaternion's 10 distinct entries of q q^T, an angle's cosine and
    sine, a value as it is."""
    v = x[:, feature.columns]
    if feature.kind == "rotation" and len(feature.columns) == 3:  # roll, pitch, yaw: as the same rotation's q
        v = _euler_quaternions(v)
    if feature.kind == "rotation":
        with np.errstate(all="ignore"):
            q = v / np.linalg.norm(v, axis=1, keepdims=True)
        iu = np.triu_indices(4)
        return (q[:, :, None] * q[:, None, :])[:, iu[0], iu[1]]
    if feature.kind == "angle":
        return np.concatenate([np.cos(v), np.sin(v)], 1)
    if feature.kind == "relative":
        return v[:, :1] - v[:, 1:]
    return v


def _euler_quaternions(rpy: np.ndarray) -> np.ndarray:
    """[N, 4] the unit quaternions of [N, 3] roll, pitch and yaw (about the fixed x, y and z axes, in that order:
    the robotics convention); NaN where an angle is."""
    from scipy.spatial.transform import Rotation

    out = np.full((len(rpy), 4), np.nan)
    ok = np.isfinite(rpy).all(axis=1)
    if ok.any():
        out[ok] = Rotation.from_euler("xyz", rpy[ok]).as_quat()
    return out
