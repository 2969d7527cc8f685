"""Training-step throughput of PETNet's controllers on this machine: frame-samples per second of ``PETNet.loss``
(with the object read-out) and an Adam step on random tensors of a training batch's shapes, one line per
controller, all in the same run.

    python benchmarks/controller_speed.py --batch-tasks 32 --timesteps 16

The controllers are those docs/results.md compares (the controller section): feature points off a 16x16 or a
32x32 map (``fine_points``), 16 or 32 channels, z shifting the first convolution or tiled onto the image.
"""

from __future__ import annotations

import argparse
import time

import torch

from democheck.petnet.blocks import ModelConfig
from democheck.petnet.model import build_model

CONTROLLERS = {
    "points 16x16, 16 ch, shift": dict(task_fusion="shift"),
    "points 32x32, 16 ch, shift": dict(task_fusion="shift", fine_points=True),
    "points 32x32, 32 ch, shift": dict(task_fusion="shift", fine_points=True, conv_channels=32),
    "points 32x32, 32 ch, tile": dict(task_fusion="tile", fine_points=True, conv_channels=32),
}


def samples_per_s(b: int, k: int, steps: int, warmup: int, **kw) -> float:
    torch.manual_seed(0)
    cfg = ModelConfig(image_size=64, state_dim=17, action_dim=7, keypoints=True, readout_dim=6, **kw)
    model = build_model(cfg)
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    batch = {"cue": torch.randint(0, 255, (b, 2, 64, 64, 3), dtype=torch.uint8),
             "frames": torch.randint(0, 255, (b, k, 64, 64, 3), dtype=torch.uint8),
             "state": torch.randn(b, k, 17), "actions": torch.randn(b, k, 7), "env_state": torch.randn(b, k, 6)}
    for i in range(warmup + steps):
        if i == warmup:
            t0 = time.perf_counter()
        loss = model.loss(batch, readout_weight=1.0)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    return b * k * steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch-tasks", type=int, default=32)
    ap.add_argument("--timesteps", type=int, default=16)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--warmup", type=int, default=2)
    args = ap.parse_args()
    print(f"{torch.get_num_threads()} threads, batch {args.batch_tasks} x {args.timesteps}")
    for name, kw in CONTROLLERS.items():
        rate = samples_per_s(args.batch_tasks, args.timesteps, args.steps, args.warmup, **kw)
        print(f"{name}: {rate:,.0f} frame-samples/s; 7M frame-samples in {7e6 / rate / 3600:.1f} h", flush=True)


if __name__ == "__main__":
    main()
