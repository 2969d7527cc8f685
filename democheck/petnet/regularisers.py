"""Optional terms of PETNet's training objective, in one table.

The paper's loss is ``PETNet.loss`` (behavioural cloning under z drawn from
the cue's task posterior).  Each entry of ``REGULARISERS`` adds one named
term to it, weighted by a training recipe's ``[regularisers]`` table
(``democheck/recipes/train/``; weight 0 = off): the weighted sum is the loss.
Terms are computed, and summed, in the table's order.

Every term here was measured on the pushing suite; what each bought, and
what did not work, is in its docstring and in the model card.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.nn.functional as F

from democheck.errors import DemocheckError
from democheck.petnet.blocks import cue_input
from democheck.petnet.model import hinge_embedding_loss, kl_diag
from democheck.petnet.posterior import product_of_gaussians


def task_matching_loss(mu_c: torch.Tensor, var_c: torch.Tensor, mu_t: torch.Tensor, var_t: torch.Tensor,
                       task: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy of finding each cue's own task among the batch's tasks by Gaussian likelihood.

    Candidate j's task mean is scored under cue i's posterior widened by j's own variance,
    log N(mu_t_j; mu_c_i, var_c_i + var_t_j).  The variance gets a direct gradient: a cue whose mean lands
    among the wrong tasks lowers its loss by widening, a cue that pins its task down by narrowing.  ``task``
    ([B] task ids) leaves out the candidates of the cue's own task other than its match: a batch of fewer
    tasks than items (a dataset of few tasks) holds no wrong match among them, and one task holds none at all.
    """
    v = var_c[:, None] + var_t[None]  # [B, B, z]
    logp = -0.5 * (((mu_c[:, None] - mu_t[None]) ** 2) / v + torch.log(v)).sum(-1)
    if task is not None:
        same = (task[:, None] == task[None]) & ~torch.eye(len(task), dtype=torch.bool, device=task.device)
        if same.any():
            logp = logp.masked_fill(same, float("-inf"))
    return F.cross_entropy(logp, torch.arange(len(mu_c), device=mu_c.device))


def broken_cues(cue: torch.Tensor) -> torch.Tensor:
    """Cues no demonstration can produce, made from a batch of real ones (uint8 [B, 2, H, W, C]): each cue's
    first frame with the next cue's last frame (two scenes; the batch's cues are of different tasks), and each
    cue played backwards.  Neither is a defect kind democheck injects or probes, so the benchmark stays unseen.
    """
    spliced = torch.stack([cue[:, 0], cue.roll(-1, 0)[:, 1]], dim=1)
    return torch.cat([spliced, cue.flip(1)])


def broken_cue_loss(sigma_real: torch.Tensor, sigma_broken: torch.Tensor, margin: float = math.log(2.0)
                    ) -> torch.Tensor:
    """Hinge on log task standard deviations ([N] each, the mean over dimensions): every broken cue must be at
    least ``exp(margin)`` times as uncertain as the batch's real cues on average.  Both sides get the gradient --
    broken cues up, real ones down -- so the loss ranks without setting a scale; the task-matching loss, which
    wants real cues sure of their task, sets it.  Two variants ran away or collapsed (push-v1, from
    petnet-push-v1, weight 1): with the real cues as a fixed reference, every rise leaked into them through the
    shared weights and sigma ran away (mean val sigma 56 after 500 steps, 4,700 after 3,000); with the prior's
    sigma 1 as the target, all cues rose to 1.3 together and task matching fell to chance (val 3.34 = ln 28).
    """
    return F.relu(margin - (sigma_broken.log() - sigma_real.log().mean())).mean()


@dataclass
class Step:
    """What the terms of one step share: the batch, the cue's posterior, and posteriors computed on first use."""

    encoder: torch.nn.Module
    batch: dict[str, torch.Tensor]
    mu: torch.Tensor | None = None
    var: torch.Tensor | None = None
    sigma: torch.Tensor | None = None
    teacher: torch.nn.Module | None = None  # the frozen starting encoder (``partial_kl``)
    _seen: dict[str, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict)

    def posterior(self, key: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(mu, var) of the batch's cues under ``key``: ``traj_cue`` (the trajectory's own cue), ``partial_cue``."""
        if key not in self._seen:
            self._seen[key] = self.encoder(cue_input(self.batch[key]))
        return self._seen[key]

    def joint(self, mu: torch.Tensor, var: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q(z | cue, target): the product of the cue's and the trajectory's own cue's posteriors."""
        mu_t, var_t = self.posterior("traj_cue")
        return product_of_gaussians(torch.stack([mu, mu_t]), torch.stack([var, var_t]))


def _kl_prior(s: Step) -> dict[str, torch.Tensor]:
    return {"kl_prior": kl_diag(s.mu, s.var, torch.zeros_like(s.mu), torch.ones_like(s.var)).mean()}


def _kl_np(s: Step) -> dict[str, torch.Tensor]:
    mu_q, var_q = s.joint(s.mu, s.var)
    return {"kl_np": kl_diag(mu_q, var_q, s.mu, s.var).mean()}


def _task_matching(s: Step) -> dict[str, torch.Tensor]:
    return {"task_matching": task_matching_loss(s.mu, s.var, *s.posterior("traj_cue"), s.batch.get("task"))}


def _partial_cue(s: Step) -> dict[str, torch.Tensor]:
    mu_p, var_p = s.posterior("partial_cue")
    return {"partial_cue": task_matching_loss(mu_p, var_p, *s.posterior("traj_cue"), s.batch.get("task")),
            "partial_sigma": var_p.sqrt().mean()}


def _partial_kl(s: Step) -> dict[str, torch.Tensor]:
    if s.teacher is None:
        raise ValueError("the partial-cue KL needs the frozen starting encoder (a recipe's init)")
    mu_p, var_p = s.posterior("partial_cue")
    with torch.no_grad():
        mu_0, var_0 = s.teacher(cue_input(s.batch["cue"]))
    return {"partial_kl": kl_diag(mu_0, var_0, mu_p, var_p).mean(), "partial_sigma": var_p.sqrt().mean()}


def _broken_cue(s: Step) -> dict[str, torch.Tensor]:
    _, var_b = s.encoder(cue_input(broken_cues(s.batch["cue"])))
    return {"broken_cue": broken_cue_loss(s.sigma.mean(-1), var_b.sqrt().mean(-1)), "broken_sigma": var_b.sqrt().mean()}


def _mean_hinge(s: Step) -> dict[str, torch.Tensor]:
    mu_t, _ = s.posterior("traj_cue")
    return {"mean_hinge": hinge_embedding_loss(F.normalize(s.mu, dim=-1), F.normalize(mu_t, dim=-1))}


@dataclass(frozen=True)
class Regulariser:
    name: str  # the recipe key and the term's name in the loss history
    description: str
    term: Callable[[Step], dict[str, torch.Tensor]]  # {name: the term, and diagnostics that are not summed}
    partial_cues: bool = False  # batches must carry cues cut short (``Batches.sample(partial=True)``)
    needs_init: bool = False  # needs a starting model (a recipe's ``init``), whose encoder it holds fixed


REGULARISERS: dict[str, Regulariser] = {r.name: r for r in (
    Regulariser("kl_prior", "KL(q(z | cue) || N(0, I)): the task posterior pulled towards a unit prior", _kl_prior),
    Regulariser("kl_np", "Neural-Process KL(q(z | cue, target) || q(z | cue)); z is then drawn from q(z | cue, "
                "target)", _kl_np),
    Regulariser("task_matching", "find each cue's task among the batch's by Gaussian likelihood, so mu carries the "
                "task and var says how well (``task_matching_loss``)", _task_matching),
    Regulariser("partial_cue", "the task-matching loss on cues cut at a random time (first frame + a frame "
                "before the end), so var grows with what a cue leaves out", _partial_cue, partial_cues=True),
    Regulariser("partial_kl", "KL(q0(z | cue) || q(z | the cue cut at a random time)), q0 the starting encoder "
                "held fixed: a cut cue must cover every task it could be.  Measured and not shipped: 5,000 steps "
                "at weight 1 from petnet-push-v1 left sigma flat over the cut time and made mu ignore the last "
                "frame; its target must stay fixed (taken from the encoder being trained, sigma ran away: 2.6e7 "
                "after 3,000 steps)", _partial_kl, partial_cues=True, needs_init=True),
    Regulariser("broken_cue", "a hinge making broken cues (two scenes spliced, or played backwards) at least twice "
                "as uncertain as real ones (``broken_cue_loss``)", _broken_cue),
    Regulariser("mean_hinge", "TecNets' hinge loss on the unit-normalised task means", _mean_hinge),
)}


def check_weights(weights: dict[str, float]) -> None:
    """One clear line for an unknown regulariser or a negative weight."""
    unknown = sorted(set(weights) - set(REGULARISERS))
    if unknown:
        raise DemocheckError(f"unknown regulariser {', '.join(unknown)}; known: {', '.join(REGULARISERS)}")
    bad = [f"{k} = {v}" for k, v in weights.items() if not (isinstance(v, (int, float)) and v >= 0)]
    if bad:
        raise DemocheckError(f"regulariser weights are numbers >= 0 (0 = off), not {', '.join(bad)}")
    if weights.get("kl_prior", 0) > 0 and weights.get("kl_np", 0) > 0:
        raise DemocheckError("kl_prior and kl_np are two choices of one KL term; set one of them")


def active(weights: dict[str, float]) -> list[Regulariser]:
    """The regularisers a recipe turns on, in the table's order."""
    return [r for name, r in REGULARISERS.items() if weights.get(name, 0) > 0]


def objective(model: torch.nn.Module, batch: dict[str, torch.Tensor], weights: dict[str, float],
              sample: bool = True, teacher: torch.nn.Module | None = None, tecnet_margin: float = 0.1,
              tecnet_weight: float = 10.0, readout: float = 0.0) -> dict[str, torch.Tensor]:
    """The whole training objective of a batch: the model's own loss plus the weighted regularisers
    (``loss``), with every term and diagnostic by name.  A TecNets model has its own objective and no
    regularisers.  ``readout``: the weight of the controller's environment-state read-out, either model."""
    if model.cfg.model_type != "petnet":
        return model.loss(batch, sample, margin=tecnet_margin, hinge_weight=tecnet_weight, readout_weight=readout)
    regs = active(weights)
    step = Step(model.encoder, batch, teacher=teacher)

    def terms(mu: torch.Tensor, var: torch.Tensor, sigma: torch.Tensor) -> dict[str, torch.Tensor]:
        step.mu, step.var, step.sigma = mu, var, sigma
        out: dict[str, torch.Tensor] = {}
        for r in regs:
            out.update(r.term(step))
        return out

    out = model.loss(batch, sample, z_posterior=step.joint if weights.get("kl_np", 0) > 0 else None, terms=terms,
                     readout_weight=readout)
    for r in regs:
        out["loss"] = out["loss"] + weights[r.name] * out[r.name]
    return out
