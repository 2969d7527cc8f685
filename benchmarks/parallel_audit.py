"""The audit with one worker process, with two, and on Ray Data: the same scores, and how much faster.

    python benchmarks/parallel_audit.py DATASET [MODEL] [--ray] [--two-nodes] [--no-model]

Audits DATASET (with MODEL, default the shipped one) with ``workers=1`` and ``workers=2`` (and with ``--ray``
on a local 2-CPU Ray instance, ``engine="ray"``, its start-up included; with ``--two-nodes`` on a Ray cluster of
two nodes of one CPU each -- a head and a second node that joins it, as ``ray start --head`` and ``ray start
--address`` make one, here both on this machine -- reached by its address as a real cluster is), checks that
every column of the score tables is identical to the one-worker table, and prints the cue pass's, the decoding
pass's and the whole audit's wall time for each and their ratios to one worker (both passes run in the same
workers).
"""

import os
import time

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

from democheck.audit.run import audit  # noqa: E402
from democheck.data import open_dataset  # noqa: E402
from democheck.petnet.checkpoint import load_checkpoint  # noqa: E402

def two_nodes():
    """A Ray cluster of two nodes of one CPU each on this machine (``ray.cluster_utils.Cluster``: a head, then a
    node joining it with its own resources), to be reached by its address."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    return cluster


def measure(dataset, model=None, ray: bool = False, verbose: bool = False, nodes: bool = False,
            no_model: bool = False) -> dict:
    """Audit ``dataset`` with 1 and 2 local workers (and 2 Ray actors with ``ray``, 2 nodes with ``nodes``): per
    setup the cue pass's, the decoding pass's and the whole audit's seconds, and whether every column equals one
    worker's."""
    ds = open_dataset(dataset)
    ckpt = None if no_model else load_checkpoint(model)
    setups = {"1 worker": (1, "local"), "2 workers": (2, "local")}
    if ray:
        setups["Ray, 2 actors"] = (2, "ray")
    if nodes:
        setups["Ray, 2 nodes"] = (2, "ray")
    runs = {}
    for name, (workers, engine) in setups.items():
        cluster = two_nodes() if name == "Ray, 2 nodes" else None
        t0 = time.perf_counter()
        try:
            table, summary = audit(ds, ckpt, workers=workers, engine=engine,
                                   ray_address=cluster.address if cluster else None)
        finally:
            if cluster is not None:
                import ray

                ray.shutdown()
                cluster.shutdown()
        runs[name] = (table, time.perf_counter() - t0, summary["timing"])
    base = runs["1 worker"]
    out = {"demos": len(ds), "setups": {}}
    for name, (table, wall, timing) in runs.items():
        differ = [c for c in base[0].columns
                  if not (np.array_equal(np.stack(base[0][c].to_numpy()), np.stack(table[c].to_numpy()))
                          if c in ("sigma", "mu") else base[0][c].equals(table[c]))]
        out["setups"][name] = {"cues_s": timing["score_s"], "decoding_s": timing["actions_s"], "whole_s": wall,
                               "ratio": base[1] / wall, "identical": not differ, "differ": differ}
        if verbose:
            cues = (f"cues {timing['score_s']:5.1f} s (x{base[2]['score_s'] / timing['score_s']:.2f}), "
                    if ckpt is not None else "")
            ratio = base[2]["actions_s"] / timing["actions_s"]
            print(f"  {name:<14} {cues}decoding {timing['actions_s']:6.1f} s (x{ratio:.2f}),"
                  f" whole audit {wall:6.1f} s (x{base[1] / wall:.2f}); scores identical to 1 worker: {not differ}"
                  + (f" (differ: {differ})" if differ else ""), flush=True)
    return out


if __name__ == "__main__":  # spawned workers import this file again
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("model", nargs="?", help="a model folder or a shipped model's name (default: the shipped one)")
    ap.add_argument("--ray", action="store_true", help="also on a local 2-CPU Ray instance")
    ap.add_argument("--two-nodes", action="store_true", help="also on a Ray cluster of two nodes of one CPU each")
    ap.add_argument("--no-model", action="store_true", help="the model-free checks alone")
    args = ap.parse_args()
    print(f"{args.dataset}:")
    measure(args.dataset, args.model, ray=args.ray, verbose=True, nodes=args.two_nodes, no_model=args.no_model)
