"""The epistemic part of PETNet's task variance: how far a cue lies from the cues the model was trained on.

The paper's variance head is trained on real cues only, so what it says about a cue unlike any of them is an
accident of its weights (on the shipped model a black image got a *smaller* task variance than any demo).  As in
deep deterministic uncertainty (Mukhoti et al. 2021), the head keeps the data's ambiguity, and a density over
features of the training inputs says how far the network can be trusted at all.  The density is one Gaussian
(Ledoit-Wolf shrinkage covariance) over:

- a *cue autoencoder*'s features (``train_cue_autoencoder``: a conv stack shaped like the task encoder's, trained
  after the model to reconstruct its training cues as they are) of the cue's *last frame*, shown in both places
  (``NOVELTY_VIEW``, the model's ``novelty_view``): how familiar the demo's end looks.  The task encoder's own
  features drop what the task does not need, so an empty scene falls inside them; a reconstruction keeps what
  is in the picture.  The first frame, an ordinary start, would dilute an unusual end.
- the demo's state at its last step (``fit_novelty``'s end states, the model's ``novelty_state``), each dimension
  standardised over the training demos' ends (``end_state_units``): a frame cannot show an arm that left the
  view, and one Gaussian over both reads the state's surprise given what the frame shows.  A dataset without
  state dimensions keeps the frame alone.

The cue's squared Mahalanobis distance d2 becomes variance in task space (``TaskEncoder``): var_novel = prior_var *
d2 / d2_ref, prior_var the variance of z over the training cues (the spread of their means plus their mean
variance), d2_ref the ``QUANTILE`` of d2 over held-out real cues (the ``val`` split; where the model learnt every
demo, ``train.finish_rows``, the fitted cues): nine in ten real cues of new tasks get less than one prior's worth
of variance, an image of nothing tens to hundreds.

How each part was chosen: docs/decisions.md ("The model's task uncertainty"); what else was tried: the model card.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from democheck.errors import DemocheckError
from democheck.petnet.blocks import NOVELTY_VIEWS, conv_out_dim, conv_stack, cue_input, novelty_input

# The reference distance d2_ref: this quantile of the held-out cues' d2 (docs/decisions.md, "The novelty part's
# reference distance").
QUANTILE = 0.9
NOVELTY_VIEW = "last"  # what the density reads of a cue: its last frame, in both places (see the module docstring)
# The cue autoencoder: Adam at AUTOENCODER_LR on batches of AUTOENCODER_BATCH cues for AUTOENCODER_EPOCHS passes
# over the training cues, at most AUTOENCODER_STEPS steps (a dataset of 100 cues: 63 steps).
AUTOENCODER_STEPS = 3000
AUTOENCODER_EPOCHS = 40
AUTOENCODER_BATCH = 64
AUTOENCODER_LR = 1e-3


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


@torch.no_grad()
def stack_features(conv: nn.Module, cues: np.ndarray, device: torch.device, chunk: int = 256, view: str = "cue"
                   ) -> np.ndarray:
    """A conv stack's flattened features [N, D] of what ``view`` reads (``model.novelty_input``) of uint8 cues
    [N, 2, H, W, 3]."""
    out = [conv(novelty_input(cue_input(torch.from_numpy(np.ascontiguousarray(cues[s:s + chunk])).to(device)), view))
           .float().cpu().numpy() for s in range(0, len(cues), chunk)]
    return np.concatenate(out) if out else np.zeros((0, 0), np.float32)


def autoencoder_steps(n_cues: int, cap: int | None = None) -> int:
    """Steps of ``train_cue_autoencoder`` for ``n_cues`` training cues: ``AUTOENCODER_EPOCHS`` passes over them,
    at most ``cap`` (default ``AUTOENCODER_STEPS``), at least one."""
    cap = AUTOENCODER_STEPS if cap is None else cap
    return int(min(cap, max(1, -(-AUTOENCODER_EPOCHS * n_cues // AUTOENCODER_BATCH))))


def train_cue_autoencoder(cues: np.ndarray, cfg: Any, device: torch.device, steps: int, seed: int = 0,
                          on_progress: Callable[[int, int], None] | None = None, decoder: nn.Module | None = None
                          ) -> tuple[nn.Module, float]:
    """A conv stack shaped like the task encoder's (``model.conv_stack``) trained with a decoder of transposed
    convolutions to reconstruct uint8 cues [N, 2, H, W, 3] (mean squared error on the network's input scale,
    Adam, batches of ``AUTOENCODER_BATCH`` drawn by ``seed``); the encoder in eval mode, and the last
    ``AUTOENCODER_BATCH`` steps' mean loss.  Only the encoder is kept: its features carry the novelty density
    (``decoder``: train this one, e.g. ``cue_decoder(cfg)``, to keep it; default a new one)."""
    rng = np.random.default_rng([seed, 0xAE])
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        enc = conv_stack(6, cfg).to(device, memory_format=torch.channels_last)
        dec = (cue_decoder(cfg) if decoder is None else decoder).to(device)
    opt = torch.optim.Adam(list(enc.parameters()) + list(dec.parameters()), lr=AUTOENCODER_LR)
    recent: deque[float] = deque(maxlen=AUTOENCODER_BATCH)  # the last steps' losses
    with torch.enable_grad():  # a caller may hold no_grad (evaluation code fits densities too)
        for step in range(1, steps + 1):
            rows = rng.integers(0, len(cues), size=min(AUTOENCODER_BATCH, len(cues)))
            x = cue_input(torch.from_numpy(np.ascontiguousarray(cues[np.sort(rows)])).to(device))
            out = dec(enc(x))
            if out.shape[-2:] != x.shape[-2:]:  # an image side that halving and doubling do not give back
                out = F.interpolate(out, size=x.shape[-2:], mode="bilinear", align_corners=False)
            loss = F.mse_loss(out, x)
            opt.zero_grad()
            loss.backward()
            opt.step()
            recent.append(float(loss.detach()))
            if on_progress is not None:
                on_progress(step, steps)
    return enc.eval(), float(np.mean(recent)) if recent else float("nan")


def cue_decoder(cfg: Any) -> nn.Sequential:
    """From the conv stack's flattened [C * s * s] features back to a [6, H, W] cue: one 4x4 transposed
    convolution that doubles the side per conv layer, ReLU between them."""
    side = int(round((conv_out_dim(cfg) / cfg.conv_channels) ** 0.5))
    layers: list[nn.Module] = [nn.Unflatten(1, (cfg.conv_channels, side, side))]
    for i in range(cfg.conv_layers):
        last = i == cfg.conv_layers - 1
        layers.append(nn.ConvTranspose2d(cfg.conv_channels, 6 if last else cfg.conv_channels, 4, 2, 1))
        if not last:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def end_state_units(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centre and unit of each dimension of the training demos' end states [N, S] for the novelty density:
    their mean and standard deviation (1 for a dimension that does not vary, which then stays put)."""
    states = np.asarray(states, np.float64)
    mean, spread = states.mean(0), states.std(0)
    return mean, np.where(spread > 1e-6 * (1.0 + np.abs(mean)), spread, 1.0)


def fit_novelty(model: torch.nn.Module, train_cues: np.ndarray, held_out_cues: np.ndarray, device: torch.device,
                quantile: float = QUANTILE, trim: float = 0.0, autoencoder: int | None = None, seed: int = 0,
                on_progress: Callable[[int, int], None] | None = None, view: str = NOVELTY_VIEW,
                train_states: np.ndarray | None = None, held_out_states: np.ndarray | None = None) -> dict[str, Any]:
    """Fit the feature density of a PETNet model's encoder on ``train_cues`` and its reference distance on
    ``held_out_cues`` (real cues of tasks it was not fitted on), in place; sets ``model.cfg.novelty``.
    ``train_states``, ``held_out_states``: the same demos' states at their last step [N, S]; given (and S > 0),
    the density reads them beside the image features (``cfg.novelty_state``), each dimension standardised by
    the training demos' ends.

    ``autoencoder``: the steps of the cue autoencoder whose encoder's features the density is over
    (``train_cue_autoencoder``; None: ``autoencoder_steps`` of the training cues; 0: none, the density over the
    task encoder's own conv features, as models before it).  ``view``: what of each cue they are features of
    (``NOVELTY_VIEW``); the autoencoder learns from the cues as they are either way.

    ``trim``: fit, leave out that share of the training cues farthest from the fit, and fit again -- for
    training data that may hold the very demos an audit is to find (a user's own dataset): a covered camera
    seen in 3% of the training cues would otherwise be familiar.  (The cue autoencoder learns from every training
    cue; the trim leaves the outliers out of the density only.)

    Returns what the model card reports: the counts, the reference distance and held-out d2 quantiles.
    """
    from sklearn.covariance import LedoitWolf

    if getattr(model.cfg, "model_type", None) != "petnet":
        raise DemocheckError("only a PETNet model has a task variance to widen")
    dim = model.encoder.head[0].in_features
    if view not in NOVELTY_VIEWS:
        raise DemocheckError(f"unknown novelty view {view!r}; views: {', '.join(NOVELTY_VIEWS)}")
    if len(train_cues) < 2 or len(held_out_cues) < 1:
        raise DemocheckError(f"fitting the novelty density needs at least 2 training cues and 1 held-out cue "
                             f"(got {len(train_cues)} and {len(held_out_cues)})")
    if (train_states is None) != (held_out_states is None):
        raise DemocheckError("the novelty density reads end states of both the training and the held-out cues or of "
                             "neither")
    with_state = train_states is not None and np.asarray(train_states).shape[-1] > 0
    if with_state:
        train_states, held_out_states = (np.asarray(x, np.float64) for x in (train_states, held_out_states))
        if train_states.shape != (len(train_cues), model.cfg.state_dim) or \
                held_out_states.shape != (len(held_out_cues), model.cfg.state_dim):
            raise DemocheckError(f"end states of shape {train_states.shape} and {held_out_states.shape} for "
                                 f"{len(train_cues)} and {len(held_out_cues)} cues of a {model.cfg.state_dim}-d state")
        state_mean, state_scale = end_state_units(train_states)
    encoder = model.encoder
    steps = autoencoder_steps(len(train_cues)) if autoencoder is None else int(autoencoder)
    ae: dict[str, Any] = {"steps": steps}
    _, mus, var_task = conv_features(encoder, train_cues, device)
    if steps > 0:
        conv, ae["loss"] = train_cue_autoencoder(train_cues, model.cfg, device, steps, seed, on_progress)
    else:
        conv = None
    reader = encoder.conv if conv is None else conv
    feats, held = (stack_features(reader, c, device, view=view).astype(np.float64) for c in (train_cues, held_out_cues))
    if with_state:
        feats, held = (np.concatenate([f, (x - state_mean) / state_scale], 1)
                       for f, x in ((feats, train_states), (held, held_out_states)))
    density = LedoitWolf().fit(feats)
    if trim > 0:
        d2 = density.mahalanobis(feats)
        keep = d2 <= np.quantile(d2, 1.0 - trim)
        density = LedoitWolf().fit(feats[keep])
    d2_held = density.mahalanobis(held)
    ref = float(np.quantile(d2_held, quantile))
    if not np.isfinite(ref) or ref <= 0:
        raise DemocheckError(f"the held-out cues' feature distances are degenerate (reference {ref})")
    # Only now is the model changed: a fit that fails leaves it as it was.
    model.cfg.novelty, model.cfg.novelty_autoencoder, model.cfg.novelty_view = True, conv is not None, view
    model.cfg.novelty_state = with_state
    if conv is None and hasattr(encoder, "novelty_conv"):
        del encoder.novelty_conv
    for name in ("feature_mean", "feature_precision", "novelty_ref", "prior_var", "end_state_mean", "end_state_scale"):
        if name in encoder._buffers:  # a density fitted before, perhaps over other features: registered anew
            delattr(encoder, name)
    encoder.add_novelty()
    if conv is not None:
        encoder.novelty_conv.load_state_dict(conv.state_dict())
    as_t = lambda x: torch.as_tensor(np.asarray(x, np.float32), device=encoder.feature_mean.device)  # noqa: E731
    encoder.feature_mean.copy_(as_t(density.location_))
    encoder.feature_precision.copy_(as_t(density.precision_))
    encoder.novelty_ref.copy_(as_t(ref))
    if with_state:
        encoder.end_state_mean.copy_(as_t(state_mean))
        encoder.end_state_scale.copy_(as_t(state_scale))
    prior_var = mus.var(0) + var_task.mean(0)  # the spread of z over the training cues (law of total variance)
    encoder.prior_var.copy_(as_t(prior_var))
    return {"train_cues": len(train_cues), "held_out_cues": len(held_out_cues), "feature_dim": dim, "trim": trim,
            "features": "cue autoencoder" if steps > 0 else "task encoder", "view": view, "autoencoder": ae,
            "end_state": bool(with_state),
            "quantile": quantile, "d2_ref": ref, "shrinkage": float(density.shrinkage_),
            "held_out_d2": {f"q{int(q * 100)}": float(np.quantile(d2_held, q)) for q in (0.05, 0.5, 0.95, 0.99)},
            "prior_sd": np.sqrt(prior_var).round(4).tolist()}
