"""The epistemic part of PETNet's task variance: how far a cue lies from the cues the model was trained on.

The paper's variance head is trained on real cues only, so what it says about
a cue unlike any of them is an accident of its weights (on the shipped model
a black image got a *smaller* task variance than any demo).  Deep
deterministic uncertainty (Mukhoti et al. 2021) separates the two: the head
keeps the data's ambiguity, and a density over the network's features, fitted
on the training inputs, says how much the network can be trusted at all.

Here the density is one Gaussian over the encoder's flattened conv features
(Ledoit-Wolf shrinkage covariance: 256 dimensions, a few thousand cues), and
the cue's squared Mahalanobis distance d2 from it becomes variance in task
space (``TaskEncoder``): var_novel = prior_var * d2 / d2_ref, with prior_var
the variance of z over the training cues (the spread of their means plus
their mean variance: what z is known to be before a cue is read) and d2_ref
the ``QUANTILE`` of d2 over held-out real cues (the ``val`` split): nine in
ten real cues of new tasks get less than one prior's worth of variance, and
an image of nothing gets tens to hundreds.  The conv features were chosen over the fully
connected layers' on a development set (``push-v1-dev`` + probes): their d2
ranked idle and covered cues above real ones (AUROC 0.99, 1.00) where the
last hidden layer's did not (0.53, 1.00).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from democheck.errors import DemocheckError
from democheck.petnet.model import cue_input

# Of the held-out cues' d2: the reference distance.  On the development set (push-v1-dev + probes, shipped
# model), quantiles 0.5 / 0.9 / 0.99 gave sigma AUROC over all kinds 0.741 / 0.738 / 0.720 (no-action 0.987 /
# 0.985 / 0.835) and suspicion 0.965 / 0.970 / 0.971.
QUANTILE = 0.9


@torch.no_grad()
def conv_features(encoder: torch.nn.Module, cues: np.ndarray, device: torch.device, chunk: int = 256
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(flattened conv features [N, D], the head's task means and variances [N, z]) of uint8 cues [N, 2, H, W, 3]."""
    feats, mus, var_task = [], [], []
    for s in range(0, len(cues), chunk):
        h = encoder.conv(cue_input(torch.from_numpy(np.ascontiguousarray(cues[s:s + chunk])).to(device)))
        feats.append(h.float().cpu().numpy())
        mu, var = encoder.head_posterior(h)
        mus.append(mu.cpu().numpy())
        var_task.append(var.cpu().numpy())
    return np.concatenate(feats), np.concatenate(mus), np.concatenate(var_task)


def fit_novelty(model: torch.nn.Module, train_cues: np.ndarray, held_out_cues: np.ndarray, device: torch.device,
                quantile: float = QUANTILE, trim: float = 0.0) -> dict[str, Any]:
    """Fit the feature density of a PETNet model's encoder on ``train_cues`` and its reference distance on
    ``held_out_cues`` (real cues of tasks it was not fitted on), in place; sets ``model.cfg.novelty``.

    ``trim``: fit, leave out that share of the training cues farthest from the fit, and fit again -- for
    training data that may hold the very demos an audit is to find (a user's own dataset): a covered camera
    seen in 3% of the training cues would otherwise be familiar.

    Returns what the model card reports: the counts, the reference distance and held-out d2 quantiles.
    """
    from sklearn.covariance import LedoitWolf

    if getattr(model.cfg, "model_type", None) != "petnet":
        raise DemocheckError("only a PETNet model has a task variance to widen")
    dim = model.encoder.head[0].in_features
    if len(train_cues) < 2 or len(held_out_cues) < 1:
        raise DemocheckError(f"fitting the novelty density needs at least 2 training cues and 1 held-out cue "
                             f"(got {len(train_cues)} and {len(held_out_cues)})")
    encoder = model.encoder
    feats, mus, var_task = conv_features(encoder, train_cues, device)
    density = LedoitWolf().fit(feats.astype(np.float64))
    if trim > 0:
        d2 = density.mahalanobis(feats.astype(np.float64))
        keep = d2 <= np.quantile(d2, 1.0 - trim)
        density = LedoitWolf().fit(feats[keep].astype(np.float64))
    held = conv_features(encoder, held_out_cues, device)[0]
    d2_held = density.mahalanobis(held.astype(np.float64))
    ref = float(np.quantile(d2_held, quantile))
    if not np.isfinite(ref) or ref <= 0:
        raise DemocheckError(f"the held-out cues' feature distances are degenerate (reference {ref})")
    model.cfg.novelty = True
    encoder.add_novelty()
    as_t = lambda x: torch.as_tensor(np.asarray(x, np.float32), device=encoder.feature_mean.device)  # noqa: E731
    encoder.feature_mean.copy_(as_t(density.location_))
    encoder.feature_precision.copy_(as_t(density.precision_))
    encoder.novelty_ref.copy_(as_t(ref))
    prior_var = mus.var(0) + var_task.mean(0)  # the spread of z over the training cues (law of total variance)
    encoder.prior_var.copy_(as_t(prior_var))
    return {"train_cues": len(train_cues), "held_out_cues": len(held_out_cues), "feature_dim": dim, "trim": trim,
            "quantile": quantile, "d2_ref": ref, "shrinkage": float(density.shrinkage_),
            "held_out_d2": {f"q{int(q * 100)}": float(np.quantile(d2_held, q)) for q in (0.05, 0.5, 0.95, 0.99)},
            "prior_sd": np.sqrt(prior_var).round(4).tolist()}
