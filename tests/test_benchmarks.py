"""Every benchmark script still imports and explains itself (``--help``): a renamed function or a moved module
fails here rather than the day someone reruns a measurement.  The ones that run on tiny data are smoke-tested
beside the code they measure (``test_robust_checks``: shapes, clean_shapes, ranking/sweep, reasons;
``test_petnet``: controller_speed; ``test_foreign``: the generators)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p for p in (ROOT / "benchmarks").rglob("*.py")
                 if p.name not in ("test_slow.py", "record.py", "__init__.py") and "data" not in p.parts)


@pytest.mark.parametrize("path", SCRIPTS, ids=[str(p.relative_to(ROOT / "benchmarks")) for p in SCRIPTS])
def test_every_benchmark_imports_and_explains_itself(path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=180,
                         cwd=ROOT, env=env)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage" in res.stdout.lower() and len(res.stdout) > 100, res.stdout


def test_reference_purity_says_when_bad_demos_in_the_reference_set_the_flag_level():
    """A reference of 100 clean demos and 10 weakly seen bad ones above all of them: the level at --fpr 0.05 is a
    bad demo's, above every clean demo, and no clean demo is flagged where the rate expects 5."""
    import importlib.util

    import numpy as np
    import pandas as pd

    spec = importlib.util.spec_from_file_location("reference_purity", ROOT / "benchmarks" / "reference_purity.py")
    purity = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(purity)
    clean = np.linspace(0.0, 2.0, 100)
    table = pd.DataFrame({"suspicion": np.r_[clean, np.linspace(3.0, 3.9, 10), [9.0, 9.5]],
                          "reference": [True] * 110 + [False] * 2,
                          "is_anomaly": [False] * 100 + [False] * 5 + [True] * 7,
                          "label": ["clean"] * 100 + ["weak"] * 10 + ["strong"] * 2})
    out = purity.purity(table, fpr=0.05, top=5)
    assert out["bad_in_reference"] == 10 and out["reference"] == 110
    assert out["reference_level"] > out["clean_largest"] == 2.0
    assert out["clean_flagged"] == 0 and out["clean_expected"] == 5.0 and out["clean_interval"][0] > 0
    assert out["reference_most_suspect"] == ["weak"] * 5
    assert out["per_label"]["strong"] == {"demos": 2, "in_reference": 0, "flagged": 2}


def test_a_copy_with_the_robots_state_alone_reads_back_with_only_those_dimensions(tiny_dataset, tmp_path):
    """``without_env_state.py --state``: the copy's state holds only the dimensions asked for, by name or index, in
    its data, metadata and statistics, and the rest of each demo (frames, actions) is the source's."""
    import importlib.util
    import json

    import numpy as np

    from democheck.data import open_dataset

    spec = importlib.util.spec_from_file_location("without_env_state", ROOT / "benchmarks" / "without_env_state.py")
    strip = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(strip)
    src, _ = tiny_dataset
    out = tmp_path / "robot"
    strip.main([str(src), str(out), "--state", "0-1,tip.z"])
    before, after = open_dataset(src), open_dataset(out)
    assert after.state_dim == 3 and after.episodes.equals(before.episodes)
    e = before.episode_indices[0]
    a, b = after[e], before[e]
    assert a.extra["state_names"] == ["shoulder_pan.pos", "shoulder_lift.pos", "tip.z"]
    np.testing.assert_array_equal(a.state, b.state[:, [0, 1, 16]])
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(np.asarray(a.frames), np.asarray(b.frames))
    stats = json.loads((out / "meta/stats.json").read_text())["observation.state"]
    assert len(stats["mean"]) == 3
    with pytest.raises(SystemExit):
        strip.main([str(src), str(tmp_path / "bad"), "--state", "elbow"])
