"""The ``democheck`` command line: one module per group of commands, each command parses, calls one library
function (mostly ``democheck.workflows``), and prints.

Heavy libraries (mujoco, torch, rerun) are imported inside the commands, so ``democheck --help`` stays fast.
"""

# Each module registers its commands on ``app``, in this order in --help.
from democheck.cli import suite  # noqa: F401  synth, probe, info
from democheck.cli import train  # noqa: F401  train, fit-novelty
from democheck.cli import audit  # noqa: F401  audit, clean, view, demo
from democheck.cli import bench  # noqa: F401  bench, eval, dagger
from democheck.cli.common import app

__all__ = ["app"]
