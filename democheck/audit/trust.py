"""Whether a model's scores may vote in the ranking: each model score has a test the model passed or failed when
it was trained, read from its checkpoint.  A score that failed stays in the table and the report, leaves the
ranking, and the audit says why in a warning; the model-free checks still judge those demos."""

from __future__ import annotations

from typing import Any

import numpy as np

# The controller's mean squared error on held-out demos' normalised actions, above which its action error stays
# out of the ranking: 1 is what always answering the average action scores, so above 0.5 it explains less than
# half of what the demos do -- then a demo it fails to explain says little, and one that does nothing looks well
# explained.
CONTROLLER_MAX_MSE = 0.5
# A cue in which nothing happens (the first frame twice) must be more uncertain than this share of the audited
# demos' real cues, at its median, for task uncertainty to vote: else a demo where the arm does nothing looks
# like any other.  A model audited without that test (``untrusted`` given no ``still``) is judged by the means
# its training recorded: the still cues' at least STILL_MIN_RATIO times the real ones'.
STILL_QUANTILE = 0.9
STILL_MIN_RATIO = 2.0
STILL_SAMPLE = 64  # demos whose still cue the audit encodes for the test


def untrusted(meta: dict[str, Any], still: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, str]:
    """The model scores that failed their test, each with the sentence that says why (empty: none, or a model
    trained before the tests were recorded).  ``still``: the task uncertainty of still cues and of the real cues
    of the same audited demos, where the audit measured them (``run.still_cues``)."""
    metrics = meta.get("metrics") or {}
    out = {}
    mse = (metrics.get("final") or {}).get("val_mse")
    if mse is not None and mse > CONTROLLER_MAX_MSE:
        out["action_error"] = (f"the model's controller explains held-out demos' actions barely better than their "
                               f"average does (normalised error {mse:.2g}; the average scores 1): its action error "
                               "is reported, not ranked, since an arm that does nothing would look well explained")
    if still is not None and len(still[0]):
        level, real = float(np.median(still[0])), float(np.quantile(still[1], STILL_QUANTILE))
        failed = not level > real
        measured = (f"a cue of the first frame twice: median task uncertainty {level:.2g}, against {real:.2g} or "
                    f"less for {STILL_QUANTILE:.0%} of the same demos' real cues")
    else:
        sigma = metrics.get("task_sigma") or {}
        real, level = sigma.get("val demos", sigma.get("train demos")), sigma.get("still")
        failed = bool(real) and level is not None and level < STILL_MIN_RATIO * real
        measured = failed and (f"at training, a cue of the first frame twice: mean task uncertainty {level:.2g}, "
                               f"real demos {real:.2g}")
    if failed:
        out["task_uncertainty"] = (f"the model is not less sure of the task when nothing happens ({measured}): its "
                                   "task uncertainty is reported, not ranked; the motion checks find an arm that "
                                   "does nothing")
    return out
