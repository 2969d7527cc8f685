"""The model-free audit's false-flag rate on generated clean datasets of awkward shapes:

    python benchmarks/clean_shapes.py [--seeds 10-19]

audits ``tests/test_robust_checks.py``'s clean datasets (4 tasks x 50 demos: a quaternion of random sign, a
wrapped angle, a switch, a drawer, a slide piled at its stop, a fixed part, episodes of any length) at each
seed and prints the demos flagged, the largest outcome score, and the total with the binomial 95% interval at
the audit's 0.01.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.stats import binom

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.test_robust_checks import _audit, clean_dataset  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="10-19", help="first-last (inclusive)")
    args = ap.parse_args(argv)
    first, last = (int(x) for x in args.seeds.split("-"))
    flagged = total = 0
    for seed in range(first, last + 1):
        table = _audit(clean_dataset(seed))
        k = int(table["is_anomaly"].sum())
        flagged, total = flagged + k, total + len(table)
        print(f"seed {seed}: {k} of {len(table)} flagged; largest outcome {np.nanmax(table['outcome']):.3g}",
              flush=True)
    low, high = binom.interval(0.95, total, 0.01)
    print(f"{flagged} of {total} clean demos flagged ({flagged / total:.2%}); at a rate of 0.01 the 95% interval "
          f"is {low:.0f}-{high:.0f}")
    return {"flagged": flagged, "of": total}


if __name__ == "__main__":
    main()
