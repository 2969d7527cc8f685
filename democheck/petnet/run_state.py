"""A training run's state on disk, for ``--resume``: weights, Adam moments, both RNGs and the run's record.

The state lives in a work folder beside the output (``fsutil.work_dir``) and is
replaced atomically: written as ``state.tmp``, then renamed over ``state``
(the previous one kept as ``state.old`` until then, so a kill between the two
renames loses nothing).  ``democheck train`` saves it every ``ckpt_every``
steps and ``democheck dagger`` after every round.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from democheck.errors import DemocheckError


def save_state(work: Path, model, opt, step: int, rng: np.random.Generator, info: dict[str, Any]) -> None:
    """Save ``model``'s weights, ``opt``'s moments, torch's and ``rng``'s states and ``info`` (JSON) as at ``step``."""
    tmp = work / "state.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    osd = opt.state_dict()
    for i, st in osd["state"].items():
        for name, t in st.items():
            tensors[f"opt.{i}.{name}"] = t.detach().cpu().contiguous() if torch.is_tensor(t) else torch.tensor(t)
    tensors["rng.torch"] = torch.get_rng_state()
    save_file(tensors, str(tmp / "state.safetensors"))
    doc = {"step": step, "rng": rng.bit_generator.state, "param_groups": osd["param_groups"], **info}
    (tmp / "state.json").write_text(json.dumps(doc))
    cur, old = work / "state", work / "state.old"
    if cur.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(cur, old)
    os.replace(tmp, cur)
    shutil.rmtree(old, ignore_errors=True)


def load_state(work: Path, model, opt) -> tuple[int, np.random.Generator, dict[str, Any]]:
    """Restore what ``save_state`` saved into ``model``, ``opt`` and torch's RNG; returns (step, rng, info)."""
    for cand in (work / "state", work / "state.old"):  # state.old: a kill between the two renames
        if (cand / "state.json").exists() and (cand / "state.safetensors").exists():
            break
    else:
        raise DemocheckError(f"{work}: no saved training state to resume from")
    doc = json.loads((cand / "state.json").read_text())
    tensors = load_file(str(cand / "state.safetensors"))
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, v in tensors.items():
        if key.startswith("opt."):
            _, i, name = key.split(".", 2)
            state.setdefault(int(i), {})[name] = v
    opt.load_state_dict({"state": state, "param_groups": doc["param_groups"]})
    torch.set_rng_state(tensors["rng.torch"])
    rng = np.random.Generator(np.random.PCG64())
    rng.bit_generator.state = doc["rng"]
    return int(doc["step"]), rng, doc
