"""Every bad input gets one line naming the file and the problem, exit status 2, and nothing written."""

import pytest

from tests.bad_inputs import CASES, run_case


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_one_clear_line(case, tiny_dataset, tiny_model, tmp_path):
    ds, _ = tiny_dataset
    argv, code, output, exc = run_case(case, tmp_path, ds, tiny_model)
    assert code == 2, f"{argv}: exit {code}, {output!r}, {exc!r}"
    assert "Traceback" not in output
    if case.after_progress:  # the decoding's progress, then the one line
        *progress, output = output.splitlines()
        assert all(" demos" in line for line in progress), progress
    assert output.startswith("error:") and "\n" not in output, output
    assert case.expect in output, output
    assert not (tmp_path / "out").exists()  # nothing written


def test_a_task_with_a_single_demo_is_still_scored_by_audit(tmp_path, tiny_model):
    """Training needs two demos per task; the audit scores a lone demo (no consistency for it)."""
    import json
    from dataclasses import replace

    from typer.testing import CliRunner

    from democheck.cli import app
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    d = tmp_path / "one-each"
    generate(replace(TINY, demos_per_task=1), d, workers=1)
    res = CliRunner().invoke(app, ["audit", str(d), "--out", str(tmp_path / "r"), "--model", str(tiny_model)])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["demos"] == TINY.n_tasks and all(r["consistency"] is None for r in summary["top_suspects"])
