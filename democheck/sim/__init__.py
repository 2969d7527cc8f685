"""The MuJoCo pushing suite: scene, objects, environment, scripted expert, suite generation."""

import os

# Headless by default; must be set before mujoco is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")
# Mesa's software renderer (llvmpipe) splits each frame over a thread per core by default; at these frame sizes
# the threads' hand-offs cost more than they save, and every worker process would start its own set.  Rendering
# on the calling thread: push-mini's generation 2,378 -> 2,855 frames/s on 2 cores, 2 workers (medians of 3), the
# same files; one process alone (as ``eval`` and ``dagger`` render) 1,214 -> 1,787 (``benchmarks/synth_speed.py``).
# Ignored by hardware drivers; an LP_NUM_THREADS already set is kept.
os.environ.setdefault("LP_NUM_THREADS", "0")
