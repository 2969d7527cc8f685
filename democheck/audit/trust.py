"""Whether a model's scores may vote in the ranking: each model score has a test the model passed or failed when
it was trained, read from its checkpoint.  A score that failed stays in the table and the report, leaves the
ranking, and the audit says why in a warning; the model-free checks still judge those demos."""

from __future__ import annotations

from typing import Any

# The controller's mean squared error on held-out demos' normalised actions, above which its action error stays
# out of the ranking: 1 is what always answering the average action scores, so above 0.5 it explains less than
# half of what the demos do -- then a demo it fails to explain says little, and one that does nothing looks well
# explained.
CONTROLLER_MAX_MSE = 0.5
# A cue in which nothing happens (the first frame twice) must be at least this many times as uncertain as real
# demos' cues, on average, for task uncertainty to vote: else a demo where the arm does nothing looks like any other.
STILL_MIN_RATIO = 2.0


def untrusted(meta: dict[str, Any]) -> dict[str, str]:
    """The model scores that failed their test, each with the sentence that says why (empty: none, or a model
    trained before the tests were recorded)."""
    metrics = meta.get("metrics") or {}
    out = {}
    mse = (metrics.get("final") or {}).get("val_mse")
    if mse is not None and mse > CONTROLLER_MAX_MSE:
        out["action_error"] = (f"the model's controller explains held-out demos' actions barely better than their "
                               f"average does (normalised error {mse:.2g}; the average scores 1): its action error "
                               "is reported, not ranked, since an arm that does nothing would look well explained")
    sigma = metrics.get("task_sigma") or {}
    real, still = sigma.get("val demos", sigma.get("train demos")), sigma.get("still")
    if real and still is not None and still < STILL_MIN_RATIO * real:
        out["task_uncertainty"] = (f"the model is not much less sure of the task when nothing happens (a cue of the "
                                   f"first frame twice: task uncertainty {still:.2g}, real demos {real:.2g}): its "
                                   "task uncertainty is reported, not ranked; the motion checks find an arm that "
                                   "does nothing")
    return out
