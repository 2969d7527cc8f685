"""Whether a model's scores may vote in the ranking: each model score has a test -- the controller's, from its
training record; task uncertainty's, the novelty's and the consistency's, on the audited data where they can be
-- and a score that failed stays in the table and the report, leaves the ranking, and the audit says why in a
warning; the model-free checks still judge those demos."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

# The controller's mean squared error on held-out demos' normalised actions, above which its action error stays
# out of the ranking: 1 is what always answering the average action scores, so above 0.5 it explains less than
# half of what the demos do -- then a demo it fails to explain says little, and one that does nothing looks well
# explained.
CONTROLLER_MAX_MSE = 0.5
# Task uncertainty votes only where the model is clearly less sure of the task when (almost) nothing happens: the
# median task uncertainty of such demos at least STILL_MIN_RATIO times the others' median.  Such demos are, in
# order: those of the audited data whose arm the motion check finds hardly moving (at least IDLE_MIN_DEMOS of
# them); else cues cut short -- a demo's first frame and the one STILL_AT of the way in, as if it had stopped
# there (a recorded idle demo is not its first frame twice: an arm settles after reset); else, without a camera,
# the still cues (the first frame twice) the model's training recorded, by their means.
STILL_MIN_RATIO = 2.0
IDLE_MIN_DEMOS = 2
STILL_AT = 0.1
STILL_SAMPLE = 64  # demos whose cut cue the audit encodes for the test
# The novelty and the consistency vote where the model reads the audited demos' own cues played backwards (their
# last frame first, the state they began in as their end) as clearly unlike the real ones: the median of the
# backwards cues at least BACKWARDS_MIN_RATIO times the same demos' real cues' median (the task uncertainty's
# factor).  A model that cannot tell a demo's end from its beginning has nothing to say about how a demo ended: a
# reset recorded as a demo, an object knocked over; one that can is heard on any dataset, of one task or many.
BACKWARDS_MIN_RATIO = STILL_MIN_RATIO
READS_BACKWARDS = ("novelty", "consistency")


def backwards_tests(backwards: dict[str, tuple[np.ndarray, np.ndarray]] | None) -> dict[str, dict[str, Any]]:
    """What the backwards test read, per score of ``READS_BACKWARDS`` that it measured (``untrusted``'s
    ``backwards``): the medians over the demos played backwards and as recorded, how many, and whether it votes --
    for the audit's summary, whether the score passed or not."""
    out = {}
    for name, values in (backwards or {}).items():
        back, real = (v[np.isfinite(v)] for v in (np.asarray(v, np.float64) for v in values))
        if len(back) and len(real):
            level, usual = float(np.median(back)), float(np.median(real))
            out[name] = {"backwards": level, "as_recorded": usual, "demos": len(back),
                         "votes": bool(level >= BACKWARDS_MIN_RATIO * usual)}
    return out


def untrusted(meta: dict[str, Any],
              still: tuple[np.ndarray, np.ndarray] | Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
              idle: tuple[np.ndarray, np.ndarray] | None = None,
              backwards: dict[str, tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, str]:
    """The model scores that failed their test, each with the sentence that says why (empty: none, or a model
    trained before the tests were recorded).  ``still``: the task uncertainty of cut cues and of the real cues
    of the same audited demos, where the audit measured them (``run.still_cues``; a callable is called only when
    ``idle`` does not decide); ``idle``: the task uncertainty of the demos whose arm the motion check finds hardly
    moving and of the others; ``backwards``: per score of ``READS_BACKWARDS``, its values on demos' cues played
    backwards and on the same demos' real cues (``run.backwards_cues``); a score not measured so keeps its vote,
    as the ranking recipe gives it."""
    metrics = meta.get("metrics") or {}
    out = {}
    for name, test in backwards_tests(backwards).items():
        if name in READS_BACKWARDS and not test["votes"]:
            out[name] = (f"the model reads demos played backwards hardly unlike the same demos (median {name} "
                         f"{test['backwards']:.2g} backwards, {test['as_recorded']:.2g} as recorded, of "
                         f"{test['demos']} demos; it should be at least {BACKWARDS_MIN_RATIO:g} times): its {name} "
                         "is reported, not ranked")
    mse = (metrics.get("final") or {}).get("val_mse")
    if mse is not None and mse > CONTROLLER_MAX_MSE:
        out["action_error"] = (f"the model's controller explains held-out demos' actions barely better than their "
                               f"average does (normalised error {mse:.2g}; the average scores 1): its action error "
                               "is reported, not ranked, since an arm that does nothing would look well explained")
    if idle is not None and len(idle[0]) >= IDLE_MIN_DEMOS and len(idle[1]):
        level, real = float(np.median(idle[0])), float(np.median(idle[1]))
        measured = (f"the {len(idle[0])} demos whose arm hardly moves: median task uncertainty {level:.2g}, the "
                    f"others' {real:.2g}")
    elif still is not None and len((still := still() if callable(still) else still)[0]):
        level, real = float(np.median(still[0])), float(np.median(still[1]))
        measured = (f"demos cut {STILL_AT:.0%} of the way in: median task uncertainty {level:.2g}, the same demos "
                    f"whole {real:.2g}")
    else:
        sigma = metrics.get("task_sigma") or {}
        real, level = sigma.get("val demos", sigma.get("train demos")), sigma.get("still")
        measured = (f"at training, a cue of the first frame twice: mean task uncertainty {level:.2g}, real demos "
                    f"{real:.2g}") if real and level is not None else ""
    failed = bool(measured) and not level >= STILL_MIN_RATIO * real
    if failed:
        out["task_uncertainty"] = (f"the model is not clearly less sure of the task when almost nothing happens "
                                   f"({measured}; it should be at least {STILL_MIN_RATIO:g} times): its task "
                                   "uncertainty is reported, not ranked; the motion checks find an arm that does "
                                   "nothing")
    return out
