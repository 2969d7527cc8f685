"""The epistemic part of PETNet's task variance: how far a cue lies from the cues the model was trained on.

The paper's variance head is trained on real cues only, so what it says about
a cue unlike any of them is an accident of its weights (on the shipped model
a black image got a *smaller* task variance than any demo).  Deep
deterministic uncertainty (Mukhoti et al. 2021) separates the two: the head
keeps the data's ambiguity, and a density over the network's features, fitted
on the training inputs, says how much the network can be trusted at all.

Here the density is one Gaussian over the flattened features of a *cue
autoencoder*'s encoder (``train_cue_autoencoder``: the task encoder's conv
shape, trained after the model to reconstruct its training cues; Ledoit-Wolf
shrinkage covariance: 256 dimensions, a few thousand cues; with the demo's
state at its last step after them, below), and
the cue's squared Mahalanobis distance d2 from it becomes variance in task
space (``TaskEncoder``): var_novel = prior_var * d2 / d2_ref, with prior_var
the variance of z over the training cues (the spread of their means plus
their mean variance: what z is known to be before a cue is read) and d2_ref
the ``QUANTILE`` of d2 over held-out real cues (the ``val`` split; where the
model learnt every demo, ``train.finish_rows``, over the fitted cues
themselves): nine in ten real cues of new tasks get less than one prior's
worth of variance, and an image of nothing gets tens to hundreds.

Why an autoencoder's features and not the task encoder's own: the task loss
makes the encoder's features keep what tells tasks apart and drop the rest,
and an empty scene, or a scene where the arm flailed and no object moved,
falls inside what they span -- on the development set (``push-v1-dev`` +
probes) the density over the shipped encoder's conv features ranked
no-objects and random probes at AUROC 0.42 and 0.64 (below chance for the
empty scenes), and neither other densities over them, an ensemble of
encoders, nor an encoder trained to read out the objects' positions did
better (the model card).  Features trained to reconstruct the cue keep what
is in it: the same Gaussian over them ranked no-objects 0.996, random 0.990,
no-action 0.998, hidden 1.000, occluded 0.997 (each kind's mean 10 to 1,000
clean standard deviations above the clean demos') after 3,000 steps; 6,000
steps, twice the time, gave 0.995, 0.993, 0.999, 1.000, 0.999.  The
reconstruction error itself does not (no-objects 0.54, random 0.43: an
emptier scene is easier to draw).  ``benchmarks/novelty_features.py``.  Over the
autoencoder's features, other densities (per task, nearest neighbours, per
position), an ensemble of three autoencoders, a frame autoencoder trained on
every step of the demos and one trained on partial cues too read random
probes no higher (0.95-0.99 on three development draws; the model card): a
flung arm's cue is about as unusual to them as the most unusual clean cues of
new tasks.
What the density reads of a cue (``NOVELTY_VIEW``, the model's ``novelty_view``): its *last frame*, shown to
the autoencoder in both places -- how familiar the demo's end looks.  Every demo's first frame is an ordinary
start (objects at rest, the arm at home), and in the whole cue that familiar half dilutes an unusual end, while
a held-out object makes the start as unfamiliar as the end: that is how the clean demos of new tasks reached as
far as a flung arm.  The same autoencoder and Gaussian over the last frame, on three development draws pooled
(push-v1-dev, -dev3, -dev4 with their probes; ``benchmarks/feature_density_choices.py``), d2 alone random /
no-objects: the whole cue 0.981 / 0.991, the last frame 0.988 / 0.993, the first frame 0.680 / 0.212 (an empty
start is *more* familiar), the last frame's given the first's (a likelihood ratio against the start) 0.987 /
0.993; the whole task uncertainty of the shipped model refitted so, benched on each draw: random 0.970, 0.956,
0.964 -> 0.986, 0.974, 0.986, no-objects and no-action the same or higher, occluded 1.000 -> 0.999 at worst
(the model card).  The autoencoder learns from the cues as they are.
And where the demo ended (``fit_novelty``'s end states, the model's ``novelty_state``): the density is one Gaussian
over the last frame's features and the demo's state at its last step, each state dimension standardised over the
training demos' ends (``end_state_units``).  A frame cannot show an arm that left the view -- the least unusual
random probes end in a frame with less in it than a real one, the objects where they started -- and the state
says where it is; one Gaussian over both reads the state's surprise *given* what the frame shows.  On the three
development draws (``benchmarks/end_state_choices.py``, this model's autoencoder, draw 2; then each draw benched
with the model refitted so), the whole task uncertainty random 0.986, 0.974, 0.986 -> 1.000 on all three,
no-action 0.998, 0.998, 1.000 -> 1.000, no-objects 0.994, 0.985, 0.995 -> 0.997, 0.989, 0.996, gave-up 0.990,
0.982, 0.989 -> 0.997, 0.990, 0.994, occluded 0.999, 0.999, 1.000 -> 0.999, 0.996, 0.998, hidden 1.000; the
ranking the same or higher.  Two separate Gaussians summed instead (the state's d2 and the frame's, each over its
reference) lost occluded (0.979 against 0.998 on draw 2: a clean demo's ordinary frame no longer excuses its
unusual state); the state alone reads hidden and occluded at 0.44 and 0.95.  What it costs: the end states are
read from the data files, no frame decoded -- 0.20 s of a 0.99 s cue pass over push-v1-fresh's 768 demos
(``end_state_choices.py --time``), nothing in training.
Meta-World mw2-dev and the one-task mw2-one-dev (their your-data models refitted both ways as their training
fits the density, on every demo, ``train.finish_rows``): the whole task uncertainty over all kinds 0.806 -> 0.841
and 0.840 -> 0.868, random 0.849 -> 0.919 and 0.85 -> 0.90, gave-up 0.754 -> 0.821 and 0.81 -> 0.87, occluded
1.000 either way and 0.96 -> 0.88; the ranking the same.  A dataset without state dimensions keeps the frame alone.
Before, the conv features had been chosen over the fully connected layers'
(their d2 ranked idle and covered cues above real ones, AUROC 0.99, 1.00,
where the last hidden layer's did not, 0.53, 1.00).
"""

from __future__ import annotations

from collections import deque
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from democheck.errors import DemocheckError
from democheck.petnet.model import NOVELTY_VIEWS, conv_out_dim, conv_stack, cue_input, novelty_input

# Of the held-out cues' d2: the reference distance.  On the development set (push-v1-dev + probes, shipped
# model), quantiles 0.5 / 0.9 / 0.99 gave sigma AUROC over all kinds 0.741 / 0.738 / 0.720 (no-action 0.987 /
# 0.985 / 0.835) and suspicion 0.965 / 0.970 / 0.971.
QUANTILE = 0.9
# The cue autoencoder: Adam at AUTOENCODER_LR on batches of AUTOENCODER_BATCH cues for AUTOENCODER_EPOCHS passes
# over the training cues, at most AUTOENCODER_STEPS steps (push-v1's 4,800 training cues: 3,000 steps, 2.5 min
# on 2 cores; a dataset of 100 cues: 63 steps).
NOVELTY_VIEW = "last"  # see the module docstring
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
