"""A model folder from a training run's saved state (``.<out>.partial/state``, written every ``ckpt_every`` steps),
to evaluate a run part-way (``democheck eval OUT --data DATA --split train --trials 1``):

    python benchmarks/partial_model.py runs/.petnet-push-v2.partial data/push-v2 runs/petnet-push-v2-step8000

The weights at the state's step; the normalisation fitted again on DATA's training rows, as ``train`` fits it.
The folder holds no novelty density, gate or reference (``finish_petnet`` writes those at the end of a run):
``eval`` without ``--gate`` reads it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from safetensors.torch import load_file

from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.petnet.checkpoint import save_checkpoint
from democheck.petnet.blocks import ModelConfig
from democheck.petnet.model import build_model
from democheck.petnet.train import Normalisation, task_rows


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("work", type=Path, help="the run's .<out>.partial folder")
    ap.add_argument("data", type=Path, help="the dataset the run trains on")
    ap.add_argument("out", type=Path)
    args = ap.parse_args(argv)
    doc = json.loads((args.work / "state/state.json").read_text())
    cfg = ModelConfig(**doc["model_config"])
    model = build_model(cfg)
    tensors = load_file(str(args.work / "state/state.safetensors"))
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    arrays = build_cache(open_dataset(args.data))
    rows = np.concatenate(list(task_rows(arrays, "train", doc["train_config"]["seed"]).values()))
    spans = np.concatenate([np.arange(arrays.offsets[r], arrays.offsets[r] + arrays.lengths[r]) for r in rows])
    norm = Normalisation.fit(arrays.state[spans], arrays.actions[spans])
    save_checkpoint(args.out, model.eval(), cfg, norm, {"data": str(args.data), "training": {
        "step": doc["step"], "steps": doc["train_config"]["steps"], "wall_s": doc["wall_s"],
        "history": doc.get("history", []), "partial": True}})
    print(f"{args.out}: the weights at step {doc['step']} of {doc['train_config']['steps']}")
    return args.out


if __name__ == "__main__":
    main()
