"""democheck's performance record for this machine, in one command.

    python benchmarks/run.py --data data/push-v1 --repeats 3 --out benchmarks/results.json

Prints a markdown table of:
- generation frames/s (``democheck synth``) and its ratio to the bare
  step+render loop on the same episodes (``synth_speed.py``);
- training samples/s (``democheck train``'s loop) and its ratio to a bare
  forward/backward/Adam loop on the same shapes (``train_speed.py``);
- audit demos/s (model load and t-SNE apart) and peak memory on the dataset
  and on a 10x replica (``audit_scale.py``);
- the default audit (cue and decoding passes) with 1 and 2 worker processes, and
  with 2 Ray actors where Ray is installed, each with its ratio to 1 worker and
  whether the scores are identical (``parallel_audit.py``);
- the training and audit figures again on the GPU when one is present.

Every figure is the median of ``--repeats`` runs; each ratio is taken within
one run (baseline and democheck interleaved), so machine noise cancels.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def machine() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB, {gpu}; torch {torch.__version__}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("data/push-v1"), help="a push-v1-sized suite (for train and audit)")
    ap.add_argument("--suite", default="push-mini", help="recipe timed for generation")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--times", type=int, default=10, help="size of the audit's large replica")
    ap.add_argument("--workdir", type=Path, default=None, help="for the replica (same filesystem as --data)")
    ap.add_argument("--out", type=Path, default=None, help="also write the figures as JSON here")
    args = ap.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    if not (args.data / "meta/info.json").exists():
        raise SystemExit(f"{args.data}: no dataset; make it with: democheck synth push-v1 --out {args.data}")

    import torch

    import audit_scale
    import parallel_audit
    import synth_speed
    import train_speed
    from democheck.sim.suite import load_recipe

    res: dict = {"machine": machine()}
    print(f"machine: {res['machine']}", flush=True)
    res["synth"] = synth_speed.measure(load_recipe(args.suite), workers=min(2, os.cpu_count() or 1),
                                       repeats=args.repeats, verbose=True)
    res["train_cpu"] = train_speed.measure(str(args.data), repeats=args.repeats, device_name="cpu", verbose=True)
    res["audit_cpu"] = audit_scale.measure(args.data, args.times, repeats=args.repeats, workdir=args.workdir,
                                           device="cpu", verbose=True)
    try:
        import ray.data  # noqa: F401
        has_ray = True
    except ImportError:
        has_ray = False
    res["audit_workers"] = parallel_audit.measure(args.data, ray=has_ray, verbose=True)
    if torch.cuda.is_available():
        res["train_cuda"] = train_speed.measure(str(args.data), repeats=args.repeats, device_name="cuda", verbose=True)
        res["audit_cuda"] = audit_scale.measure(args.data, args.times, repeats=args.repeats, workdir=args.workdir,
                                                device="cuda", verbose=True)
    print()
    print(table(res, args))
    if args.out:
        args.out.write_text(json.dumps(res, indent=2))


def table(res: dict, args) -> str:
    s = res["synth"]
    rows = [f"Machine: {res['machine']}. Medians of {args.repeats} runs.", "",
            "| what | figure | baseline in the same run | ratio |", "|---|---:|---:|---:|",
            f"| generation ({s['suite']}, {s['workers']} workers) | {s['synth_fps']:.0f} frames/s | bare step+render "
            f"{s['bare_fps']:.0f} frames/s | {s['ratio']:.2f} |"]
    for dev in ("cpu", "cuda"):
        t = res.get(f"train_{dev}")
        if t:
            rows.append(f"| training ({dev}) | {t['train_samples_per_s']:.0f} samples/s | bare fwd/bwd/Adam "
                        f"{t['bare_samples_per_s']:.0f} samples/s | {t['ratio']:.2f} |")
    for dev in ("cpu", "cuda"):
        a = res.get(f"audit_{dev}")
        if a:
            big = f"{args.times}x"
            rows.append(f"| audit ({dev}), {a['1x']['demos']} demos | {a['1x']['demos_per_s']:.0f} demos/s, peak "
                        f"{a['1x']['peak_rss_mb']:.0f} MB | model load {a['1x']['model_load_s']:.2f} s, t-SNE "
                        f"{a['1x']['tsne_s']:.1f} s | |")
            rows.append(f"| audit ({dev}), {a[big]['demos']} demos | {a[big]['demos_per_s']:.0f} demos/s, peak "
                        f"{a[big]['peak_rss_mb']:.0f} MB | peak memory vs {a['1x']['demos']} demos | "
                        f"{a['memory_ratio']:.2f} |")
    w = res.get("audit_workers")
    if w:
        one = w["setups"]["1 worker"]
        for name, r in w["setups"].items():
            if name != "1 worker":
                rows.append(f"| default audit, {w['demos']} demos, {name} | {r['whole_s']:.1f} s (scores identical: "
                            f"{'yes' if r['identical'] else 'NO'}) | 1 worker {one['whole_s']:.1f} s | "
                            f"{r['ratio']:.2f} |")
    return "\n".join(rows)


if __name__ == "__main__":
    main()
