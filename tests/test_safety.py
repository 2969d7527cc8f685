"""Inputs are read-only, untrusted files never run code, and readers fail only with democheck's own error."""

import hashlib
import re
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from democheck.cli import app
from democheck.data import open_dataset
from democheck.errors import DemocheckError

runner = CliRunner()
PACKAGE = Path(__file__).resolve().parents[1] / "democheck"


def _digest(root: Path) -> dict[str, str]:
    """sha256 of every file under root, and the set of paths (so added files count too)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_no_command_writes_inside_the_dataset_it_reads(tiny_dataset, tiny_model, tmp_path):
    src, _ = tiny_dataset
    ds = tmp_path / "ds"
    shutil.copytree(src, ds)
    before = _digest(ds)
    m = str(tiny_model)
    commands = [
        ["info", str(ds)],
        ["audit", str(ds), "--out", str(tmp_path / "report"), "--model", m],
        ["probe", str(ds), "--out", str(tmp_path / "probes"), "--per-kind", "1", "--workers", "1"],
        ["bench", str(ds), str(tmp_path / "probes"), "--out", str(tmp_path / "bench"), "--model", m],
        ["train", str(ds), "--out", str(tmp_path / "model"), "--steps", "2", "--set", "batch_tasks=2", "--set", "timesteps=2",
         "--device", "cpu", "--cache-dir", str(tmp_path / "cache")],
        ["eval", m, "--data", str(ds), "--out", str(tmp_path / "eval"), "--split", "train", "--trials", "1",
         "--workers", "1"],
    ]
    for argv in commands:
        res = runner.invoke(app, argv)
        assert res.exit_code == 0, (argv, res.output)
        assert _digest(ds) == before, f"{argv[0]} changed the dataset"


def test_no_unsafe_deserialisation_in_the_package():
    """Checkpoints load through safetensors and JSON only: no pickles, no eval, no unsafe YAML anywhere."""
    banned = re.compile(r"torch\.load\(|pickle\.loads?\(|(?<![.\w])eval\(|(?<![.\w])exec\(|yaml\.load\(|yaml\.unsafe_load|"
                        r"np\.load\([^)]*allow_pickle=True")
    hits = [f"{p.relative_to(PACKAGE)}:{i}" for p in PACKAGE.rglob("*.py")
            for i, line in enumerate(p.read_text().splitlines(), 1) if banned.search(line)]
    assert hits == []


# ---------------------------------------------------------------------------
# property tests: arbitrary bytes in each file of a dataset
# ---------------------------------------------------------------------------

def _files_of(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def pristine(tiny_dataset, tmp_path_factory):
    src, _ = tiny_dataset
    return src, _files_of(src)


def _exercise(root: Path) -> None:
    """Everything a command reads: metadata, every episode (data and frames), every cue."""
    ds = open_dataset(root)
    for e in ds.episode_indices:
        ds[e]
        ds.cue_frames(e)
    ds.cue_frames_many(ds.episode_indices)


def _mutated_copy(src: Path, tmp: Path, rel: str, data: bytes) -> Path:
    dst = tmp / "ds"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    (dst / rel).write_bytes(data)
    return dst


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_arbitrary_bytes_in_any_file_raise_only_democheck_errors(pristine, tmp_path, data):
    src, files = pristine
    rel = data.draw(st.sampled_from(files), label="file")
    original = (src / rel).read_bytes()
    mode = data.draw(st.sampled_from(["random", "truncate", "flip"]), label="mode")
    if mode == "random":
        blob = data.draw(st.binary(max_size=4096), label="bytes")
    elif mode == "truncate":
        blob = original[: data.draw(st.integers(0, max(len(original) - 1, 0)), label="keep")]
    else:
        pos = data.draw(st.integers(0, max(len(original) - 1, 0)), label="pos")
        blob = bytearray(original)
        if blob:
            blob[pos] ^= data.draw(st.integers(1, 255), label="xor")
        blob = bytes(blob)
    root = _mutated_copy(src, tmp_path, rel, blob)
    try:
        _exercise(root)
    except DemocheckError as exc:
        assert "\n" not in str(exc)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                        lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children,
                                                                                            max_size=4),
                        max_leaves=12),
       key=st.sampled_from(["features", "fps", "codebase_version", "video_path", "data_path", "chunks_size"]))
def test_arbitrary_json_values_in_info_json_raise_only_democheck_errors(pristine, tmp_path, doc, key):
    import json

    src, _ = pristine
    info = json.loads((src / "meta/info.json").read_text())
    info[key] = doc
    root = _mutated_copy(src, tmp_path, "meta/info.json", json.dumps(info).encode())
    try:
        _exercise(root)
    except DemocheckError as exc:
        assert "\n" not in str(exc)


def test_atomic_output_leaves_nothing_on_failure_and_clears_what_killed_runs_left(tmp_path):
    from democheck.fsutil import atomic_output_dir

    out = tmp_path / "report"
    with pytest.raises(RuntimeError):
        with atomic_output_dir(out) as tmp:
            (tmp / "half.txt").write_text("half")
            raise RuntimeError("interrupted")
    assert not out.exists() and not list(tmp_path.iterdir())
    dead = tmp_path / ".report.tmp-999999999"  # what a SIGKILLed run leaves: a hidden folder of a gone process
    dead.mkdir()
    with atomic_output_dir(out) as tmp:
        (tmp / "done.txt").write_text("done")
    assert (out / "done.txt").read_text() == "done" and not dead.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["report"]


def test_a_frame_rate_no_recorder_runs_at_is_refused_in_one_line(pristine, tmp_path):
    """An fps of 1e300 is finite and positive, yet no frame number it gives fits a frame index: refused when the
    dataset is opened, not as an overflow when its video is decoded."""
    import json

    src, _ = pristine
    info = json.loads((src / "meta/info.json").read_text())
    info["fps"] = 1e300
    root = _mutated_copy(src, tmp_path, "meta/info.json", json.dumps(info).encode())
    with pytest.raises(DemocheckError, match="fps must be a positive number up to"):
        open_dataset(root)
