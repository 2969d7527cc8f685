"""Rung (b) of the controller's ladder: can a policy that *sees* clone the expert when it is told the task?

    python benchmarks/visual_bc.py data/push-v2 --out runs/visual-bc [--steps 20000] [--aux 1] [--resume]
        [--rollouts 200] [--device cpu|cuda]
    python benchmarks/visual_bc.py data/push-v2 --out runs/locate --steps 3000 --objects-only [--sharp]
        [--posed 20] [--context 2] [--channels 32]
    python benchmarks/visual_bc.py data/push-v2 --out runs/on-points --steps 6000 --aux 0 --points-from runs/locate
        [--tune-points --aux 1]

Behaviour cloning on the train split's clean demos: the current 64x64 frame, the robot state and the task given
as an oracle code (the target's and the distractor's shape, colour and size, one-hot: which object to push is
told, where it is must be seen).  The network is MIL's design for this: convolutions, then a spatial softmax that
turns each of their channels into the expected image position of its activation (feature points, sub-pixel by
construction), joined to the state and the task code, then a 3x256 MLP to the 7 torques.  ``--aux W`` adds W x
the mean squared error of a linear read-out of the objects' positions (``observation.environment_state``: target
and distractor x, y, normalised) from the feature points -- the supervision that should make them find the
objects rather than the arm.  ``--shift N`` shifts each training frame by its own random offset of up to N
pixels (``petnet.batches.random_shift``).

The perception apart: ``--objects-only`` trains the convolutions and points on where the objects are alone (the
points and the task code through an MLP: which object is the target is the task's to say) and reports how far they
miss, in cm, on training frames and on the val split's, by the demo's step, and with the arm posed as in another
demo (``arm_swap``: does it read the objects, or the arm that heads for them?); ``--posed K`` trains it on K frames
a demo with the arm posed so half of each batch (``democheck.sim.posed``).  ``--points-from`` puts such a localiser
under the controller, frozen (or, with ``--tune-points``, trained on with it, ``--aux`` x its read-out's loss
keeping it on the objects).

Then closed loop: ``--rollouts`` episodes of 100 steps on train tasks, each on a layout no demo had (the same
layouts for every run with the same ``--seed``), success rate with its 95% interval, against the scripted
expert the demos were recorded with on the same layouts.  (The rollouts' frames are raw renders; the training
frames were decoded from the suite's H.264 video.)  Checkpoints every ``--ckpt-every`` steps in ``--out``
(``--resume`` carries on from the last); ``results.json`` there holds the numbers.  The rung asks >= 85%.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.evaluate.meta_test import wilson
from democheck.petnet.batches import random_shift
from democheck.petnet.blocks import SpatialSoftmax
from democheck.sim.catalog import COLOURS, OBJECTS, SHAPES, SIZES
from democheck.sim.env import EPISODE_STEPS, PushEnv
from democheck.sim.posed import render_layouts, render_posed
from democheck.sim.variants import make_expert, record_demo

OBJECT_XY = [0, 1, 3, 4]  # target x, y and distractor x, y in observation.environment_state


def object_code(key: str) -> np.ndarray:
    """One-hot shape, colour and size of a catalog object."""
    o = OBJECTS[key]
    return np.concatenate([np.eye(len(SHAPES))[list(SHAPES).index(o.shape)],
                           np.eye(len(COLOURS))[list(COLOURS).index(o.colour)],
                           np.eye(len(SIZES))[list(SIZES).index(o.size)]]).astype(np.float32)


def task_code(target: str, distractor: str) -> np.ndarray:
    return np.concatenate([object_code(target), object_code(distractor)])


class SharpPoints(SpatialSoftmax):
    """The spatial softmax with a learnt temperature per channel (``--sharp``): a channel can make its softmax as
    peaked as its object is small, rather than its weights having to grow for it."""

    def __init__(self, channels: int):
        super().__init__()
        self.log_temperature = nn.Parameter(torch.zeros(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x * self.log_temperature.exp()[None, :, None, None])


class VisualPolicy(nn.Module):
    def __init__(self, state_dim: int, code_dim: int, action_dim: int, channels: int = 32, sharp: bool = False,
                 context: int = 0):
        super().__init__()
        layers = [nn.Conv2d(3, channels, 5, stride=2, padding=2), nn.ReLU(),
                  nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU()]
        for d in range(context):  # ``--context``: dilated layers that let a point's channel see around its object
            layers += [nn.Conv2d(channels, channels, 3, padding=2 ** (d + 1), dilation=2 ** (d + 1)), nn.ReLU()]
        self.conv = nn.Sequential(*layers, nn.Conv2d(channels, channels, 3, padding=1))
        self.points = SharpPoints(channels) if sharp else SpatialSoftmax()
        self.mlp = nn.Sequential(nn.Linear(2 * channels + state_dim + code_dim, 256), nn.ReLU(),
                                 nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
                                 nn.Linear(256, action_dim))
        self.objects = nn.Linear(2 * channels, len(OBJECT_XY))
        # --objects-only: which point is the target is the task's to say, so the points and the code go through an MLP
        self.locate = nn.Sequential(nn.Linear(2 * channels + code_dim, 256), nn.ReLU(), nn.Linear(256, len(OBJECT_XY)))

    def keypoints(self, frames: torch.Tensor) -> torch.Tensor:
        """frames uint8 [B, H, W, 3] -> the feature points [B, 2C]."""
        return self.points(self.conv(frames.permute(0, 3, 1, 2).float() / 127.5 - 1.0))

    def forward(self, frames: torch.Tensor, state: torch.Tensor, code: torch.Tensor):
        """Returns (normalised actions, normalised object positions by the linear read-out)."""
        kp = self.keypoints(frames)
        return self.mlp(torch.cat([kp, state, code], 1)), self.objects(kp)

    def where(self, frames: torch.Tensor, code: torch.Tensor, kp: torch.Tensor | None = None) -> torch.Tensor:
        """The objects' normalised positions from the feature points (``kp``, where computed already) and the task
        code (``--objects-only``)."""
        kp = self.keypoints(frames) if kp is None else kp
        return self.locate(torch.cat([kp, code], 1))


def load(suite: Path, split: str = "train"):
    """The ``split``'s clean demos: frames (memmap), state, actions, object positions, task codes, per frame;
    and those demos' rows of the episode table (with their sim records)."""
    import pandas as pd

    ds = open_dataset(suite)
    arrays = build_cache(ds)
    table = ds.episodes
    clean = table["label"].fillna("clean") == "clean"
    order = arrays.episodes["episode_index"].to_numpy()  # the cache's episodes, in its order
    keep = [i for i, e in enumerate(order) if table.loc[e, "split"] == split and clean[e]]
    rows = np.concatenate([np.arange(arrays.offsets[i], arrays.offsets[i] + arrays.lengths[i]) for i in keep])
    env_state = {}
    for f in sorted((suite / "data").glob("*/*.parquet")):
        t = pd.read_parquet(f, columns=["episode_index", "observation.environment_state"])
        for e, g in t.groupby("episode_index"):
            env_state[int(e)] = np.stack(g["observation.environment_state"].to_numpy())[:, OBJECT_XY]
    codes, objs = [], []
    for i in keep:
        sim = json.loads(table.loc[order[i], "sim"])
        codes.append(np.repeat(task_code(sim["target"], sim["distractor"])[None], arrays.lengths[i], 0))
        objs.append(env_state[int(order[i])])
    return arrays, rows, np.concatenate(codes), np.concatenate(objs).astype(np.float32), table.loc[order[keep]]


def posed_frames(arrays, rows: np.ndarray, eps, per_demo: int, seed: int) -> tuple[np.ndarray, ...]:
    """Frames in which the arm says nothing of where the objects are (``democheck.sim.posed``): each demo's layout
    with the arm posed as at a random frame of ``rows``.  Returns frames, task codes and the objects' (target x, y,
    distractor x, y)."""
    sims = [json.loads(sim) for sim in eps["sim"]]
    frames, poses = render_posed(sims, np.asarray(arrays.state[rows])[:, :7], per_demo, seed)
    codes = np.repeat(np.stack([task_code(sim["target"], sim["distractor"]) for sim in sims]), per_demo, 0)
    return frames.reshape(-1, *frames.shape[2:]), codes, poses[:, :, [0, 1, 3, 4]].reshape(-1, 4)


def arm_swap(policy: VisualPolicy, arrays, rows: np.ndarray, eps, objs: np.ndarray, norm: dict, device,
             step: int = 50, n: int = 60) -> dict:
    """Does the localiser read the objects or the arm?  ``n`` of the demos' layouts rendered with the arm posed as
    at ``step`` of another of them: the median distance, cm, of the target read from where it stands and from that
    other demo's target (``benchmarks/arm_shortcut.py`` asks a PETNet model the same)."""
    offsets = np.asarray(arrays.offsets)
    first = np.searchsorted(rows, offsets[np.searchsorted(offsets, rows, "right") - 1])  # each row's demo's start
    starts = np.unique(first)[:n]  # positions in ``rows`` of the demos' first frames, in ``eps``' order
    donors = np.roll(starts, 1)
    sims = [json.loads(eps.iloc[k]["sim"]) for k in range(len(starts))]  # the k-th demo of ``rows`` is ``eps``' k-th
    frames, poses, _ = render_layouts(sims, np.asarray(arrays.state[rows[donors + step]])[:, None, :7])
    frames = frames[:, 0]
    codes = [task_code(sim["target"], sim["distractor"]) for sim in sims]
    own, other = poses[:, 0, :2], objs[donors + step][:, :2]
    with torch.no_grad():
        read = policy.where(torch.from_numpy(np.stack(frames)).to(device),
                            torch.from_numpy(np.stack(codes)).to(device)).cpu().numpy() * norm["os"] + norm["om"]

    def cm(truth):
        return round(float(np.median(100 * np.hypot(*(read[:, :2] - np.asarray(truth)).T))), 2)
    return {"layouts": len(frames), "cm from its own target": cm(own), "cm from the other demo's target": cm(other)}


def rollouts(policy: VisualPolicy | None, norm: dict, tasks: list[tuple[str, str]], seeds: list[int], device,
             image_size: int, expert: str) -> list[bool]:
    """Success of the policy (None: the scripted ``expert`` the demos were recorded with) on each task, each on
    the layout its seed draws."""
    env, wins = None, []
    for (target, distractor), seed in zip(tasks, seeds):
        pair = (OBJECTS[target], OBJECTS[distractor])
        if env is None:
            env = PushEnv(pair, image_size=image_size)
        else:
            env.set_task(pair)
        if policy is None:
            act = make_expert(env, expert=expert).act
        else:
            code = torch.from_numpy(task_code(target, distractor))[None].to(device)

            def act(env=env, code=code) -> np.ndarray:
                obs = env.last_obs  # what the arm sees and feels now
                s = torch.from_numpy(((obs["state"] - norm["sm"]) / norm["ss"]).astype(np.float32))[None]
                with torch.no_grad():
                    y = policy(torch.from_numpy(obs["image"].copy())[None].to(device), s.to(device), code)[0]
                return np.clip(y[0].cpu().numpy() * norm["as"] + norm["am"], -1.0, 1.0)
        wins.append(record_demo(env, act, EPISODE_STEPS, seed=seed)["success"])
    return wins


def miss_cm(policy: VisualPolicy, arrays, rows: np.ndarray, codes: torch.Tensor, objs: np.ndarray, norm: dict,
            device, n: int = 4096) -> list[float]:
    """RMS error of the read-out of the objects' positions on ``n`` frames spread over ``rows``, cm per
    coordinate."""
    pick = np.linspace(0, len(rows) - 1, min(n, len(rows))).astype(int)
    out = []
    with torch.no_grad():
        for chunk in np.array_split(pick, max(1, len(pick) // 512)):
            frames = torch.from_numpy(np.asarray(arrays.frames[rows[chunk]])).to(device)
            out.append(policy.where(frames, codes[chunk].to(device)).cpu().numpy())
    where = np.concatenate(out) * norm["os"] + norm["om"]
    return [round(float(v), 2) for v in 100 * np.sqrt(((where - objs[pick]) ** 2).mean(0))]


def miss_by_step(policy: VisualPolicy, arrays, rows: np.ndarray, codes: torch.Tensor, objs: np.ndarray, norm: dict,
                 device, n: int = 8192) -> dict:
    """The distance by which the target and the distractor are missed, cm, by the step of the demo: median and 90th
    percentile of each, on ``n`` frames spread over ``rows``."""
    pick = np.linspace(0, len(rows) - 1, min(n, len(rows))).astype(int)
    with torch.no_grad():
        where = np.concatenate([policy.where(torch.from_numpy(np.asarray(arrays.frames[rows[c]])).to(device),
                                             codes[c].to(device)).cpu().numpy()
                                for c in np.array_split(pick, max(1, len(pick) // 512))])
    miss = 100 * (where * norm["os"] + norm["om"] - objs[pick]).reshape(len(pick), 2, 2)
    dist = np.sqrt((miss ** 2).sum(2))  # [frames, (target, distractor)]
    step = rows[pick] - np.asarray(arrays.offsets)[np.searchsorted(arrays.offsets, rows[pick], "right") - 1]
    out = {}
    for lo, hi in ((0, 10), (10, 30), (30, 60), (60, 10 ** 6)):
        d = dist[(step >= lo) & (step < hi)]
        out[f"steps {lo}-{hi - 1 if hi < 10 ** 6 else ''}"] = {
            "median": [round(float(v), 2) for v in np.median(d, 0)],
            "p90": [round(float(v), 2) for v in np.percentile(d, 90, 0)]}
    out["all"] = {"median": [round(float(v), 2) for v in np.median(dist, 0)],
                  "p90": [round(float(v), 2) for v in np.percentile(dist, 90, 0)]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--aux", type=float, default=1.0)
    ap.add_argument("--shift", type=int, default=0)
    ap.add_argument("--rollouts", type=int, default=200)
    ap.add_argument("--ckpt-every", type=int, default=1000)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sharp", action="store_true", help="a learnt temperature per channel in the spatial softmax")
    ap.add_argument("--channels", type=int, default=32, help="channels of every convolution (one feature point each)")
    ap.add_argument("--context", type=int, default=0,
                    help="dilated 3x3 layers (dilation 2, 4, ...) added before the last convolution")
    ap.add_argument("--points-from", type=Path, default=None,
                    help="the --out of an --objects-only run: its convolutions and feature points, frozen; only the "
                         "controller on top of them is trained")
    ap.add_argument("--tune-points", action="store_true",
                    help="with --points-from: the points train on with the controller, --aux x the localiser's "
                         "read-out of the objects keeping them on the objects")
    ap.add_argument("--posed", type=int, default=0,
                    help="render this many frames a demo with the arm posed as in another demo (the objects where "
                         "they began), and train the localiser on them for half of each batch: the arm then cannot "
                         "stand in for the objects")
    ap.add_argument("--objects-only", action="store_true",
                    help="train the feature points on the objects' positions alone (no actions), then report how far "
                         "they miss, in cm, on training frames and on the val split's (held-out objects)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    args.out.mkdir(parents=True, exist_ok=True)

    arrays, rows, codes, objs, eps = load(args.suite)
    state, actions = arrays.state[rows], arrays.actions[rows]
    norm = {"sm": state.mean(0), "ss": state.std(0) + 1e-6, "am": actions.mean(0), "as": actions.std(0) + 1e-6,
            "om": objs.mean(0), "os": objs.std(0) + 1e-6}
    sn = torch.from_numpy((state - norm["sm"]) / norm["ss"])
    an = torch.from_numpy((actions - norm["am"]) / norm["as"])
    on = torch.from_numpy((objs - norm["om"]) / norm["os"])
    cn = torch.from_numpy(codes)
    torch.manual_seed(args.seed)
    if args.points_from:  # the localiser's shape: its channels and layers
        arch = torch.load(args.points_from / "checkpoint.pt", map_location=device, weights_only=True).get("arch", {})
        args.channels, args.context = arch.get("channels", 32), arch.get("context", 0)
        args.sharp = arch.get("sharp", args.sharp)
    policy = VisualPolicy(state.shape[1], codes.shape[1], actions.shape[1], channels=args.channels, sharp=args.sharp,
                          context=args.context).to(device)
    if args.points_from:  # a localiser's convolutions and points (``--objects-only``), kept as they are
        saved = torch.load(args.points_from / "checkpoint.pt", map_location=device, weights_only=True)["policy"]
        policy.load_state_dict({k: v for k, v in saved.items() if k.startswith(("conv.", "points.", "locate."))},
                               strict=False)
        for p in [*policy.conv.parameters(), *policy.points.parameters()] if not args.tune_points else ():
            p.requires_grad_(False)
    opt = torch.optim.Adam([p for p in policy.parameters() if p.requires_grad], args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.steps)
    step, log = 0, []
    ckpt = args.out / "checkpoint.pt"
    if args.resume and ckpt.exists():
        saved = torch.load(ckpt, map_location=device, weights_only=True)  # tensors and plain values only
        policy.load_state_dict(saved["policy"])
        opt.load_state_dict(saved["opt"])
        sched.load_state_dict(saved["sched"])
        sched.T_max = args.steps  # a longer run than the checkpoint's: the cosine stretched to the new end
        step, log = saved["step"], saved["log"]
        torch.set_rng_state(saved["torch_rng"])
    rng = np.random.default_rng(args.seed)
    if args.resume and ckpt.exists() and "batch_rng" in saved:
        rng.bit_generator.state = saved["batch_rng"]
    posed = None
    if args.posed:
        t = time.perf_counter()
        pf, pc, po = posed_frames(arrays, rows, eps, args.posed, args.seed)
        posed = (torch.from_numpy(pf), torch.from_numpy(pc), torch.from_numpy((po - norm["om"]) / norm["os"]))
        print(f"{len(pf)} posed frames rendered in {time.perf_counter() - t:.0f} s", flush=True)
    print(f"{len(rows)} frames of {len(eps)} demos; training from step {step} to {args.steps}", flush=True)
    t0, seen = time.perf_counter(), 0
    while step < args.steps:
        i = np.sort(rng.integers(0, len(rows), args.batch))
        frames = random_shift(torch.from_numpy(np.asarray(arrays.frames[rows[i]]))[:, None], args.shift)[:, 0]
        j = torch.from_numpy(i)
        if args.objects_only and posed is not None:  # half the batch from the posed frames
            half = len(i) // 2
            k = torch.from_numpy(rng.integers(0, len(posed[0]), half))
            frames = torch.cat([frames[:half], posed[0][k]])
            code, target = torch.cat([cn[j[:half]], posed[1][k]]), torch.cat([on[j[:half]], posed[2][k]])
            where, act_loss = policy.where(frames.to(device), code.to(device)), torch.zeros(())
        elif args.objects_only:
            where, act_loss = policy.where(frames.to(device), cn[j].to(device)), torch.zeros(())
        elif args.tune_points:  # the controller and the localiser's read-out on the same points
            kp = policy.keypoints(frames.to(device))
            pred = policy.mlp(torch.cat([kp, sn[j].to(device), cn[j].to(device)], 1))
            where = policy.where(frames, cn[j].to(device), kp)
            act_loss = ((pred - an[j].to(device)) ** 2).mean()
        else:
            pred, where = policy(frames.to(device), sn[j].to(device), cn[j].to(device))
            act_loss = ((pred - an[j].to(device)) ** 2).mean()
        obj_loss = ((where - (target if posed is not None and args.objects_only else on[j]).to(device)) ** 2).mean()
        loss = obj_loss if args.objects_only else act_loss + args.aux * obj_loss
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        step += 1
        seen += len(i)
        if step % 200 == 0:
            rate = seen / (time.perf_counter() - t0)
            log.append({"step": step, "action_mse": act_loss.item(), "object_mse": obj_loss.item()})
            print(f"step {step}: action mse {act_loss.item():.4f}, object mse {obj_loss.item():.4f} "
                  f"({rate:.0f} samples/s)", flush=True)
        if step % args.ckpt_every == 0 or step == args.steps:
            tmp = ckpt.with_suffix(".tmp")
            torch.save({"policy": policy.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "step": step, "log": log, "torch_rng": torch.get_rng_state(),
                        "batch_rng": rng.bit_generator.state,
                        "arch": {"channels": args.channels, "context": args.context, "sharp": args.sharp}}, tmp)
            tmp.replace(ckpt)
    train_s = time.perf_counter() - t0

    policy.eval()
    if args.objects_only:
        res = {"suite": str(args.suite), "steps": args.steps, "batch": args.batch,
               "train_s_this_run": round(train_s, 1),
               "miss_cm": {"train": miss_cm(policy, arrays, rows, cn, objs, norm, device)},
               "spread_cm": [round(float(v), 2) for v in 100 * norm["os"]]}  # the miss of guessing the mean
        varrays, vrows, vcodes, vobjs, veps = load(args.suite, "val")
        res["miss_cm"]["val"] = miss_cm(policy, varrays, vrows, torch.from_numpy(vcodes), vobjs, norm, device)
        res["val_miss_by_step_cm"] = miss_by_step(policy, varrays, vrows, torch.from_numpy(vcodes), vobjs, norm,
                                                  device)  # (target, distractor)
        res["arch"] = {"channels": args.channels, "context": args.context, "sharp": args.sharp}
        res["val_arm_of_another_demo"] = arm_swap(policy, varrays, vrows, veps, vobjs, norm, device)
        # the val split's layouts with another demo's arm: how far the points miss where the arm tells nothing
        pf, pc, po = posed_frames(varrays, vrows, veps, 4, args.seed + 1)
        with torch.no_grad():
            w = np.concatenate([policy.where(torch.from_numpy(pf[c]).to(device), torch.from_numpy(pc[c]).to(device))
                                .cpu().numpy() for c in np.array_split(np.arange(len(pf)), max(1, len(pf) // 512))])
        d = 100 * np.sqrt(((w * norm["os"] + norm["om"] - po).reshape(-1, 2, 2) ** 2).sum(2))
        res["val_posed_miss_cm"] = {"frames": len(pf), "median": [round(float(x), 2) for x in np.median(d, 0)],
                                    "p90": [round(float(x), 2) for x in np.percentile(d, 90, 0)]}
        (args.out / "results.json").write_text(json.dumps(res, indent=2))
        print(f"feature points read the objects' positions, RMS miss in cm (target x, y, distractor x, y): "
              f"train {res['miss_cm']['train']}, val {res['miss_cm']['val']}; with the arm posed as in another "
              f"demo, median target / distractor {res['val_posed_miss_cm']['median']}")
        return
    draw = np.random.default_rng([args.seed, 0xE7A1])
    picks = draw.choice(len(eps), size=args.rollouts, replace=True)
    tasks = [(json.loads(eps.iloc[k]["sim"])["target"], json.loads(eps.iloc[k]["sim"])["distractor"]) for k in picks]
    seeds = [int(s) for s in draw.integers(1 << 40, 1 << 41, args.rollouts)]  # layouts no demo was drawn from
    first = json.loads(eps.iloc[0]["sim"])
    image_size, expert_name = int(first["image_size"]), first.get("expert", "hysteresis")
    t1 = time.perf_counter()
    wins = rollouts(policy, norm, tasks, seeds, device, image_size, expert_name)
    expert = rollouts(None, norm, tasks, seeds, device, image_size, expert_name)
    res = {"suite": str(args.suite), "steps": args.steps, "aux": args.aux, "shift": args.shift, "batch": args.batch,
           "frames": int(len(rows)), "train_s_this_run": round(train_s, 1), "rollouts": args.rollouts,
           "success": float(np.mean(wins)), "success_ci95": wilson(sum(wins), len(wins)),
           "expert_success": float(np.mean(expert)), "expert_ci95": wilson(sum(expert), len(expert)),
           "rollout_s": round(time.perf_counter() - t1, 1), "log": log[-5:]}
    (args.out / "results.json").write_text(json.dumps(res, indent=2))
    lo, hi = res["success_ci95"]
    print(f"visual cloning, task given: success {res['success']:.1%} [{lo:.1%}, {hi:.1%}] over {len(wins)} rollouts "
          f"(expert on the same layouts {res['expert_success']:.1%}); results in {args.out / 'results.json'}")


if __name__ == "__main__":
    main()
