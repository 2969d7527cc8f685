"""Training throughput of democheck's loop against a bare forward/backward/Adam loop, same shapes, same run.

The bare loop feeds pre-made random tensors of the training batch's shapes to
the same model and loss; democheck's figure is ``petnet.train.train`` itself
(real (cue, trajectory) batches sampled from the decoded-frame cache), timed
between two of its progress callbacks so that start-up and the final
evaluation are left out.  The ratio says how much the data path
costs.  Samples = demonstrated-trajectory timesteps (batch_tasks x timesteps).

    python benchmarks/train_speed.py data/push-v1 --steps 60 --repeats 3
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--batch-tasks", type=int, default=16)
    ap.add_argument("--timesteps", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="auto")
    args = ap.parse_args()
    res = measure(args.dataset, args.steps, args.warmup, args.batch_tasks, args.timesteps, args.repeats, args.device,
                  verbose=True)
    print(f"median of {args.repeats} on {res['device']} ({res['threads']} threads), batch {args.batch_tasks} tasks x "
          f"{args.timesteps} timesteps: bare {res['bare_samples_per_s']:.0f} samples/s, democheck "
          f"{res['train_samples_per_s']:.0f} samples/s, ratio {res['ratio']:.2f}")


def measure(dataset: str, steps: int = 60, warmup: int = 5, batch_tasks: int = 16, timesteps: int = 8,
            repeats: int = 3, device_name: str = "auto", verbose: bool = False) -> dict:
    """Median samples/s of the bare loop and of ``train`` over ``repeats`` interleaved runs, and their ratio."""
    args = argparse.Namespace(dataset=dataset, steps=steps, warmup=warmup, batch_tasks=batch_tasks, timesteps=timesteps,
                              repeats=repeats, device=device_name)
    from democheck.data import open_dataset
    from democheck.data.cache import build_cache
    from democheck.petnet.checkpoint import Normalisation
    from democheck.petnet.blocks import ModelConfig
    from democheck.petnet.model import build_model
    from democheck.petnet.batches import Batches, task_rows, to_device
    from democheck.petnet.train import TrainConfig, objective, resolve_device, train

    device = resolve_device(args.device)
    arrays = build_cache(open_dataset(args.dataset))
    tc = TrainConfig(batch_tasks=args.batch_tasks, timesteps=args.timesteps, device=str(device))
    rows = task_rows(arrays, "train", 0)
    norm = Normalisation.fit(arrays.state[:10000], arrays.actions[:10000])
    batches = Batches(arrays, rows, norm)
    cfg = ModelConfig(image_size=arrays.frames.shape[1], state_dim=arrays.state.shape[1], action_dim=arrays.actions.shape[1])
    samples = args.batch_tasks * args.timesteps

    def run(next_batch) -> float:
        torch.manual_seed(0)
        model = build_model(cfg).to(device).train()
        opt = torch.optim.Adam(model.parameters(), lr=tc.lr)
        for i in range(args.warmup + args.steps):
            if i == args.warmup:
                if device.type == "cuda":
                    torch.cuda.synchronize()
                t0 = time.perf_counter()
            out = objective(model, next_batch(), tc)
            opt.zero_grad(set_to_none=True)
            out["loss"].backward()
            opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        return args.steps * samples / (time.perf_counter() - t0)

    def run_train() -> float:
        marks = {}

        def on_step(step, total, report):
            if step in (args.warmup, args.warmup + args.steps):
                marks[step] = time.perf_counter()

        big = 10**9  # no validation or state saving inside the timed window
        with tempfile.TemporaryDirectory() as tmp:
            train(arrays, Path(tmp) / "m", TrainConfig(steps=args.warmup + args.steps, batch_tasks=args.batch_tasks,
                                                         timesteps=args.timesteps, val_every=big, ckpt_every=big,
                                                         device=str(device)), on_progress=on_step)
        return args.steps * samples / (marks[args.warmup + args.steps] - marks[args.warmup])

    rng = np.random.default_rng(0)
    fixed = to_device(batches.sample(rng, args.batch_tasks, args.timesteps), device)
    bare_batch = {k: (torch.randint_like(v, 0, 256) if v.dtype == torch.uint8 else torch.randn_like(v))
                  for k, v in fixed.items()}
    bare, real, ratio = [], [], []
    for i in range(args.repeats):
        b = run(lambda: bare_batch)
        r = run_train()
        bare.append(b)
        real.append(r)
        ratio.append(r / b)
        if verbose:
            print(f"run {i + 1}: bare {b:7.0f} samples/s   democheck {r:7.0f} samples/s   ratio {r / b:.2f}", flush=True)
    return {"device": str(device), "threads": torch.get_num_threads(), "bare_samples_per_s": statistics.median(bare),
            "train_samples_per_s": statistics.median(real), "ratio": statistics.median(ratio), "repeats": repeats}


if __name__ == "__main__":
    main()
