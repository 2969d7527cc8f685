"""Object catalog and the task list of the pushing suite.

An object is a (shape family, colour, size) triple.  A task is an ordered
(target, distractor) pair; every pair is used in both orders (see ``_pairs``).  The meta-test split holds out whole *objects*:
a meta-test task is built only from objects that appear in no meta-training
(train or val) task, so success there measures generalisation to unseen
objects, as in the MIL sim-push benchmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

# Bump when the catalog or object geometry changes: it goes into every sim
# record so an old dataset is never re-simulated with different objects.
CATALOG_VERSION = 1

COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.10, 0.10),
    "green": (0.10, 0.65, 0.15),
    "blue": (0.12, 0.25, 0.90),
    "yellow": (0.95, 0.85, 0.10),
    "cyan": (0.10, 0.80, 0.85),
    "magenta": (0.85, 0.10, 0.80),
    "orange": (1.00, 0.50, 0.05),
    "purple": (0.45, 0.15, 0.65),
    "white": (0.95, 0.95, 0.95),
    "black": (0.08, 0.08, 0.08),
    "brown": (0.50, 0.30, 0.12),
    "pink": (1.00, 0.60, 0.70),
}

SIZES: dict[str, float] = {"small": 0.022, "large": 0.031}

# Each family lists its parts as (geom type, half sizes in units of the
# object's scale s, planar offset in units of s).  Boxes take (x, y, z) half
# sizes, cylinders (radius, half height), spheres (radius,), capsules lie
# along x and take (radius, half length), ellipsoids (x, y, z) radii.
SHAPES: dict[str, tuple[tuple[str, tuple[float, ...], tuple[float, float]], ...]] = {
    "cube": (("box", (1.0, 1.0, 1.0), (0.0, 0.0)),),
    "block": (("box", (1.5, 0.75, 0.9), (0.0, 0.0)),),
    "cylinder": (("cylinder", (1.05, 1.0), (0.0, 0.0)),),
    "sphere": (("sphere", (1.1,), (0.0, 0.0)),),
    "capsule": (("capsule", (0.75, 0.9), (0.0, 0.0)),),
    "ellipsoid": (("ellipsoid", (1.4, 0.9, 0.8), (0.0, 0.0)),),
    "cross": (("box", (1.5, 0.45, 0.8), (0.0, 0.0)), ("box", (0.45, 1.5, 0.8), (0.0, 0.0))),
    # The L is centred on its centroid so that pushing "through the centre" means something.
    "ell": (("box", (1.3, 0.45, 0.8), (0.43, -0.43)), ("box", (0.45, 1.3, 0.8), (-0.43, 0.43))),
}


@dataclass(frozen=True)
class ObjectSpec:
    """One catalog object: a shape family in a colour and a size."""

    shape: str
    colour: str
    size: str

    @property
    def name(self) -> str:
        return f"{self.size} {self.colour} {self.shape}"

    @property
    def key(self) -> str:
        return f"{self.shape}-{self.colour}-{self.size}"

    @property
    def scale(self) -> float:
        return SIZES[self.size]

    @property
    def rgba(self) -> tuple[float, float, float, float]:
        return (*COLOURS[self.colour], 1.0)

    def parts(self) -> list[tuple[str, tuple[float, ...], tuple[float, float]]]:
        """Geoms of this object in metres: (type, MuJoCo size, planar offset)."""
        s = self.scale
        return [(kind, tuple(v * s for v in half), (off[0] * s, off[1] * s)) for kind, half, off in SHAPES[self.shape]]

    @cached_property
    def half_height(self) -> float:
        """Height of the object's centre above the table."""
        heights = []
        for kind, size, _ in self.parts():
            # Boxes and ellipsoids give z as their third size; the others are round in z.
            heights.append(size[2] if kind in ("box", "ellipsoid") else size[1] if kind == "cylinder" else size[0])
        return max(heights)

    @cached_property
    def radius(self) -> float:
        """Planar bounding radius: no part of the object reaches further from its centre."""
        r = 0.0
        for kind, size, (ox, oy) in self.parts():
            if kind in ("box", "ellipsoid"):
                reach = math.hypot(size[0], size[1]) if kind == "box" else max(size[0], size[1])
            elif kind == "capsule":
                reach = size[0] + size[1]
            else:
                reach = size[0]
            r = max(r, math.hypot(ox, oy) + reach)
        return r


def catalog() -> list[ObjectSpec]:
    """Every object, in a fixed order (shape, colour, size)."""
    return [ObjectSpec(sh, c, sz) for sh in SHAPES for c in COLOURS for sz in SIZES]


OBJECTS: dict[str, ObjectSpec] = {o.key: o for o in catalog()}


@dataclass(frozen=True)
class Task:
    """An ordered (target, distractor) pair and the split it belongs to."""

    target: ObjectSpec
    distractor: ObjectSpec
    split: str

    @property
    def name(self) -> str:
        """The task string written to the dataset; it names both objects."""
        return f"push the {self.target.name} to the goal, not the {self.distractor.name}"


def split_objects(seed: int, test_fraction: float = 0.2) -> tuple[list[ObjectSpec], list[ObjectSpec]]:
    """Partition the catalog into meta-training and held-out meta-test objects."""
    objs = catalog()
    rng = np.random.default_rng([seed, 0x5EED])
    order = rng.permutation(len(objs))
    n_test = max(2, int(round(test_fraction * len(objs))))
    test = sorted((objs[i] for i in order[:n_test]), key=lambda o: o.key)
    train = sorted((objs[i] for i in order[n_test:]), key=lambda o: o.key)
    return train, test


def _pairs(objs: list[ObjectSpec], rng: np.random.Generator, n: int) -> list[tuple[ObjectSpec, ObjectSpec]]:
    """``n`` ordered (target, distractor) pairs, drawn as unordered pairs each used in both orders, adjacent.

    Both orders of a pair make the scene alone say nothing about the task: the
    same two objects appear in (A, B) and (B, A), so only *which one reached
    the goal* tells them apart.  A task encoder must then read the outcome of
    the cue, which is what makes a cue showing the wrong object pushed, or no
    push at all, stand out.  Target and distractor always differ in colour.
    """
    unordered = [(a, b) for i, a in enumerate(objs) for b in objs[i + 1:] if a.colour != b.colour]
    half = (n + 1) // 2
    if half > len(unordered):
        raise ValueError(f"asked for {n} tasks but only {2 * len(unordered)} object pairs exist")
    out = []
    for i in rng.choice(len(unordered), size=half, replace=False):
        a, b = unordered[i]
        out += [(a, b), (b, a)]
    return out[:n]


def make_tasks(n_train: int, n_val: int, n_test: int, seed: int, test_fraction: float = 0.2,
               split_seed: int | None = None) -> list[Task]:
    """The suite's tasks: train and val from meta-training objects, test from held-out ones.

    ``split_seed`` (default ``seed``) draws which objects are held out; ``seed`` draws the pairs.
    """
    train_objs, test_objs = split_objects(seed if split_seed is None else split_seed, test_fraction)
    rng = np.random.default_rng([seed, 0x7A5C])
    meta_train = _pairs(train_objs, rng, n_train + n_val)
    meta_test = _pairs(test_objs, rng, n_test)
    tasks = [Task(t, d, "train") for t, d in meta_train[:n_train]]
    tasks += [Task(t, d, "val") for t, d in meta_train[n_train:]]
    tasks += [Task(t, d, "test") for t, d in meta_test]
    return tasks
