"""Task posteriors: the Gaussian over task space a cue gives, and how several combine.

A ``TaskPosterior`` holds, for N cues, the mean ``mu`` and the two parts of
the variance (``TaskEncoder``): ``var_task``, the paper's variance head, and
``var_novel``, the novelty part (zero without a fitted density).  Their sum
``var`` is the task variance; ``task_uncertainty`` is the paper's score, the
mean over dimensions of sqrt(var).

Several cues of one task combine by the product of Gaussians,
1/var = sum_i 1/var_i, mu = var * sum_i mu_i/var_i (``product_of_gaussians``,
for numpy arrays and torch tensors alike); ``product_of_others`` is the same
product over each demo's *other* demos of its task.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


def product_of_gaussians(mu: Any, var: Any, dim: int = 0) -> tuple[Any, Any]:
    """Combine Gaussians along ``dim`` (numpy arrays or torch tensors): 1/var = sum 1/var_i, mu = var * sum mu_i/var_i."""
    precision = (1.0 / var).sum(dim)
    var_c = 1.0 / precision
    return var_c * (mu / var).sum(dim), var_c


def product_of_others(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray, k: int | None = None,
                      chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """For each demo, the product of Gaussians of the *other* demos of its task -- all of them, or its ``k``
    nearest by RMS (mu_i - mu_j) / sqrt(var_i + var_j): (m, v) [N, z], NaN for a task's only demo.

    Written with precision sums, so that the product of all others is the task's total minus the demo's own
    (linear in the task's size), and a task of thousands of demos is taken ``chunk`` demos at a time.
    """
    m_out, v_out = np.full(mu.shape, np.nan), np.full(mu.shape, np.nan)
    prec = 1.0 / var
    for task in np.unique(tasks):
        idx = np.flatnonzero(tasks == task)
        if len(idx) < 2:
            continue
        if k is None or k >= len(idx) - 1:
            p_rest = prec[idx].sum(0)[None] - prec[idx]  # precision of the others, per demo
            m_out[idx] = ((prec[idx] * mu[idx]).sum(0)[None] - prec[idx] * mu[idx]) / p_rest
            v_out[idx] = 1.0 / p_rest
            continue
        for s in range(0, len(idx), chunk):  # [chunk, n, z] at a time
            rows = idx[s:s + chunk]
            d = ((mu[rows, None] - mu[None, idx]) ** 2 / (var[rows, None] + var[None, idx])).mean(-1)
            d[np.arange(len(rows)), s + np.arange(len(rows))] = np.inf  # not itself
            nn = idx[np.argpartition(d, k - 1, axis=1)[:, :k]]  # [rows, k]
            p = prec[nn].sum(1)
            m_out[rows] = (prec[nn] * mu[nn]).sum(1) / p
            v_out[rows] = 1.0 / p
    return m_out, v_out


def task_uncertainty(var: np.ndarray) -> np.ndarray:
    """The paper's score of a task posterior with variances [..., z]: the mean over dimensions of sqrt(var)."""
    return np.sqrt(var).mean(axis=-1)


@dataclass
class TaskPosterior:
    """The task posteriors of N cues: ``mu``, ``var_task`` (the paper's head), ``var_novel`` (novelty), [N, z]."""

    mu: np.ndarray
    var_task: np.ndarray
    var_novel: np.ndarray

    @property
    def var(self) -> np.ndarray:
        """The task variance, both parts."""
        return self.var_task + self.var_novel

    @property
    def sigma(self) -> np.ndarray:
        """Task standard deviation per dimension, [N, z]."""
        return np.sqrt(self.var)

    def task_uncertainty(self, head_only: bool = False) -> np.ndarray:
        """The paper's score of each cue (``task_uncertainty``) [N]; ``head_only``: of ``var_task`` alone, without
        the novelty part."""
        return task_uncertainty(self.var_task if head_only else self.var)

    def __len__(self) -> int:
        return len(self.mu)

    def take(self, rows: Any) -> "TaskPosterior":
        return TaskPosterior(self.mu[rows], self.var_task[rows], self.var_novel[rows])

    @classmethod
    def concat(cls, parts: list["TaskPosterior"]) -> "TaskPosterior":
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("mu", "var_task", "var_novel")))

    def combined(self) -> tuple[np.ndarray, np.ndarray]:
        """The product of Gaussians of all N cues (one task): (mu, var) [z]."""
        return product_of_gaussians(self.mu, self.var)

    def others(self, tasks: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``product_of_others`` of these cues, grouped by ``tasks``."""
        return product_of_others(self.mu, self.var, tasks, k)
