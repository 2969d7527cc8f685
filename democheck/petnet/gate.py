"""The paper's safety gate: act on a cue only when its task uncertainty is within the range of real cues', else
ask for another demonstration.

The threshold is a conformal quantile of the task uncertainty (the mean task standard deviation) of real cues the
model did not train on, so a cue like them is refused at most ``false_refusal`` of the time.  Several cues of one
task combine by the product of Gaussians, which can only narrow the posterior: the robot asks again while the
combined posterior is still too wide, up to ``max_cues``.

    gate = Gate.of(checkpoint, false_refusal=0.05)
    decision = gate.decide(posterior)          # posterior of the cues shown so far (TaskPosterior)
    if decision.act: run the controller with decision.z
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from democheck.errors import DemocheckError
from democheck.petnet.posterior import TaskPosterior, task_uncertainty

DEFAULT_FALSE_REFUSAL = 0.05
MAX_REFERENCE = 2000  # cue uncertainties a checkpoint keeps for its gate


def reference_record(post: TaskPosterior, source: str) -> dict[str, Any]:
    """What a checkpoint stores for its gate: the sorted task uncertainties of real cues (at most
    ``MAX_REFERENCE``, evenly spaced quantiles beyond that) and where they came from."""
    u = np.sort(post.task_uncertainty())
    if len(u) > MAX_REFERENCE:
        u = np.quantile(u, np.linspace(0, 1, MAX_REFERENCE))
    return {"cue_uncertainty": [float(f"{x:.6g}") for x in u], "cues": int(len(post)), "source": source}


@dataclass(frozen=True)
class Decision:
    act: bool  # run the controller with ``z``; False: ask for another demonstration
    uncertainty: float  # of the combined posterior
    z: np.ndarray  # the combined posterior's mean


@dataclass(frozen=True)
class Gate:
    threshold: float  # act when the cue's task uncertainty is at most this
    false_refusal: float  # the share of real cues refused, by construction
    reference_cues: int  # how many real cues the threshold was read from
    max_cues: int = 4  # ask for more demonstrations at most until this many

    @classmethod
    def fit(cls, uncertainties: np.ndarray, false_refusal: float = DEFAULT_FALSE_REFUSAL,
            max_cues: int = 4) -> "Gate":
        """The threshold that refuses at most ``false_refusal`` of cues exchangeable with ``uncertainties``: their
        ceil((n + 1)(1 - rate))-th smallest value (a conformal quantile; +inf where n is too small to promise it)."""
        if not 0.0 < false_refusal < 1.0:
            raise DemocheckError(f"the gate's false-refusal rate is a share between 0 and 1, not {false_refusal}")
        if max_cues < 1:
            raise DemocheckError(f"the gate needs at least one cue, not {max_cues}")
        u = np.sort(np.asarray(uncertainties, np.float64))
        u = u[np.isfinite(u)]
        k = math.ceil((len(u) + 1) * (1.0 - false_refusal))
        threshold = float(u[k - 1]) if 1 <= k <= len(u) else math.inf
        return cls(threshold, false_refusal, len(u), max_cues)

    @classmethod
    def of(cls, ckpt: Any, false_refusal: float = DEFAULT_FALSE_REFUSAL, max_cues: int = 4) -> "Gate":
        """The gate of a PETNet checkpoint, from the real cues' uncertainties stored when it was trained."""
        if ckpt.config.model_type != "petnet":
            raise DemocheckError(f"{ckpt.path}: a {ckpt.config.model_type} model has no task uncertainty to gate on")
        ref = (ckpt.meta.get("gate") or {}).get("cue_uncertainty")
        if not ref:
            raise DemocheckError(f"{ckpt.path}: the model stores no reference cues for its gate (trained before "
                                 "the gate existed); fit one with Gate.fit on real cues' task uncertainty")
        return cls.fit(np.asarray(ref), false_refusal, max_cues)

    def decide(self, post: TaskPosterior) -> Decision:
        """Act or ask again, given the posteriors of every cue shown so far (combined by product of Gaussians)."""
        mu, var = post.combined()
        u = float(task_uncertainty(var))
        return Decision(u <= self.threshold, u, mu)


__all__ = ["Gate", "Decision", "reference_record", "DEFAULT_FALSE_REFUSAL"]
