"""Cohorts: `[input] path` as a glob pattern or a list of scans, one subject folder each.

The scans are 6 mm synthetic MRI heads (`make_head`) in a BIDS-like layout; most tests run only the
input stage (the engine's bookkeeping is the same for every stage), one slow test runs input,
segment and layers on two Dask workers and compares with the same subjects run in-process.
"""

import csv
import dataclasses
import json
import threading
import time

import numpy as np
import pytest

from jaxhead import io
from jaxhead.cli import main
from jaxhead.phantom import make_head
from jaxhead.run import StageError, load_config
from jaxhead.run.config import InputConfig, RunConfig
from jaxhead.run.lock import run_lock
from jaxhead.run.pipeline import run_pipeline, subject_name, subjects


def _scans(root, subs=("01", "02"), *, corrupt=(), voxel_mm=6.0):
    """BIDS-like scans root/sub-XX/anat/sub-XX_T1w.nii.gz (a different head per subject)."""
    paths = []
    for i, sub in enumerate(subs):
        d = root / f"sub-{sub}" / "anat"
        d.mkdir(parents=True, exist_ok=True)
        path = d / f"sub-{sub}_T1w.nii.gz"
        if sub in corrupt:
            path.write_bytes(b"\x1f\x8b this is not a NIfTI file")
        else:
            volume, _ = make_head("mri", voxel_mm=voxel_mm, seed=i)
            io.save_volume(volume, path)
        paths.append(path)
    return paths


def _cfg(tmp_path, path, stages=("input",), **kw):
    return RunConfig(out_dir=str(tmp_path / "run"), stages=stages,
                     input=InputConfig(source="file", path=path, voxel_mm=None, **kw))


def _table(tmp_path):
    with open(tmp_path / "run" / "subjects.csv", newline="") as f:
        return {r["subject"]: r for r in csv.DictReader(f)}


@pytest.mark.parametrize("path, name", [
    ("data/sub-01/anat/sub-01_T1w.nii.gz", "sub-01"),
    ("data/sub-01/ses-2/anat/sub-01_ses-2_T1w.nii.gz", "sub-01_ses-2"),
    ("data/sub-02/ses-b/anat/T1w.nii", "sub-02_ses-b"),  # entities from the folders
    ("scans/alice.nii.gz", "alice"),
    ("scans/bob.hdr", "bob"),
    ("scans/sub-x.y.nii.gz", "sub-x"),
])
def test_subject_names_are_bids_entities_else_the_stem(path, name):
    assert subject_name(path) == name


def test_a_pattern_and_a_list_give_one_subject_folder_per_scan(tmp_path, monkeypatch):
    paths = _scans(tmp_path / "data")
    monkeypatch.chdir(tmp_path)
    by_pattern = subjects(_cfg(tmp_path, "data/sub-*/anat/*_T1w.nii.gz"))
    assert [(s.name, s.path) for s in by_pattern] == [
        ("sub-01", "data/sub-01/anat/sub-01_T1w.nii.gz"),
        ("sub-02", "data/sub-02/anat/sub-02_T1w.nii.gz")]
    assert [s.root for s in by_pattern] == [tmp_path / "run" / "sub-01", tmp_path / "run" / "sub-02"]
    by_list = subjects(_cfg(tmp_path, tuple(str(p) for p in paths)))
    assert [s.name for s in by_list] == ["sub-01", "sub-02"]
    # one file (no pattern) keeps the single-subject folder "subject" and its config
    cfg = _cfg(tmp_path, str(paths[0]))
    assert not cfg.input.is_cohort
    [one] = subjects(cfg)
    assert (one.name, one.path, one.root) == ("subject", None, tmp_path / "run" / "subject")


def test_a_toml_list_of_scans_loads_as_a_cohort(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text('out_dir = "r"\n[input]\nsource = "file"\npath = ["a.nii.gz", "b/*.nii"]\n')
    cfg = load_config(toml)
    assert cfg.input.path == ("a.nii.gz", "b/*.nii") and cfg.input.is_cohort


def test_bad_cohorts_are_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _scans(tmp_path / "data")
    run = tmp_path / "run"
    with pytest.raises(ValueError, match=r"`path` pattern 'data/sub-\*/anat/\*_T2w.nii.gz' "
                                         r"matches no file .*check the pattern"):
        run_pipeline(_cfg(tmp_path, "data/sub-*/anat/*_T2w.nii.gz"))
    with pytest.raises(ValueError, match=r"`path` entry 'data/sub-03.nii.gz' is not a file"):
        run_pipeline(_cfg(tmp_path, ("data/sub-01/anat/sub-01_T1w.nii.gz", "data/sub-03.nii.gz")))
    # two scans of one subject: both named, and how to choose
    second = tmp_path / "data/sub-01/anat/sub-01_run-2_T1w.nii.gz"
    second.write_bytes((tmp_path / "data/sub-01/anat/sub-01_T1w.nii.gz").read_bytes())
    with pytest.raises(ValueError, match=r"'data/sub-01/anat/sub-01_T1w.nii.gz' and "
                                         r"'data/sub-01/anat/sub-01_run-2_T1w.nii.gz' are both "
                                         r"subject 'sub-01'.*narrow the pattern"):
        run_pipeline(_cfg(tmp_path, "data/sub-*/anat/*_T1w.nii.gz"))
    assert not run.exists()  # nothing was written
    with pytest.raises(ValueError, match="`labels_path` .* is one label map .* cohort"):
        _cfg(tmp_path, "data/*/anat/*.nii.gz", labels_path="labels.nii.gz")
    with pytest.raises(ValueError, match="`path` .* is set but source = 'phantom'"):
        InputConfig(path="data/sub-01/anat/sub-01_T1w.nii.gz")
    with pytest.raises(ValueError, match="`workers` = 0; use a whole number >= 1"):
        run_pipeline(_cfg(tmp_path, "data/sub-0[12]/anat/sub-0?_T1w.nii.gz"), workers=0)


def test_a_corrupt_scan_is_recorded_the_others_finish_and_a_rerun_skips(tmp_path):
    _scans(tmp_path / "data", ("01", "02", "03"), corrupt=("02",))
    cfg = _cfg(tmp_path, str(tmp_path / "data/sub-*/anat/*_T1w.nii.gz"))
    lines = []
    with pytest.raises(StageError, match=r"\[sub-02\] input: .*sub-02_T1w.nii.gz"):
        run_pipeline(cfg, progress=lines.append)
    table = _table(tmp_path)
    assert [table[s]["status"] for s in ("sub-01", "sub-02", "sub-03")] == ["done", "failed", "done"]
    assert table["sub-02"]["error"].startswith("input: ") and table["sub-01"]["error"] == ""
    assert table["sub-03"]["path"].endswith("sub-03/anat/sub-03_T1w.nii.gz")
    assert float(table["sub-01"]["seconds"]) > 0
    summary = json.loads((tmp_path / "run/summary.json").read_text())
    assert set(summary) == {"sub-01", "sub-02", "sub-03"} and "error" in summary["sub-02"]
    assert summary["sub-01"]["input"]["shape"] == list(io.load_volume(
        tmp_path / "data/sub-01/anat/sub-01_T1w.nii.gz").shape)
    for sub in ("sub-01", "sub-03"):
        assert (tmp_path / "run" / sub / "input" / "done.json").is_file()
    assert not (tmp_path / "run/sub-02/input").exists()

    # the rerun skips the finished subjects and retries the failed one, now fixed
    done_01 = (tmp_path / "run/sub-01/input/done.json").read_bytes()
    volume, _ = make_head("mri", voxel_mm=6.0, seed=1)
    io.save_volume(volume, tmp_path / "data/sub-02/anat/sub-02_T1w.nii.gz")
    lines.clear()
    results = run_pipeline(cfg, progress=lines.append)
    assert set(results) == {"sub-01", "sub-02", "sub-03"}
    assert "[sub-01] input: up to date (" in "\n".join(lines)
    assert "[sub-03] input: up to date (" in "\n".join(lines)
    assert "[sub-02] input: running (no complete earlier run)" in "\n".join(lines)
    assert (tmp_path / "run/sub-01/input/done.json").read_bytes() == done_01
    assert {r["status"] for r in _table(tmp_path).values()} == {"done"}

    # never stale: a changed scan reruns that subject's stage, and only that one
    volume, _ = make_head("mri", voxel_mm=6.0, seed=7)
    io.save_volume(volume, tmp_path / "data/sub-03/anat/sub-03_T1w.nii.gz")
    lines.clear()
    run_pipeline(cfg, progress=lines.append)
    text = "\n".join(lines)
    assert "[sub-01] input: up to date" in text and "[sub-02] input: up to date" in text
    assert "[sub-03] input: running (file " in text and "changed" in text


def test_a_subject_locked_by_another_process_is_waited_for(tmp_path):
    """A task left running by a killed driver holds its subject's lock: the next run waits for
    it instead of writing the same folder (the driver's own run lock is a different file)."""
    _scans(tmp_path / "data")
    cfg = _cfg(tmp_path, str(tmp_path / "data/sub-*/anat/*_T1w.nii.gz"))
    (tmp_path / "run").mkdir()
    lines, released = [], []
    holding = run_lock(tmp_path / "run", subject="sub-02")
    holding.__enter__()

    def release():
        time.sleep(1.5)
        released.append(time.monotonic())
        holding.__exit__(None, None, None)

    t = threading.Thread(target=release)
    t.start()
    run_pipeline(cfg, progress=lines.append)
    t.join()
    text = "\n".join(lines)
    assert "(subject sub-02) is in use by jaxhead pid" in text and "waiting" in text
    assert "[sub-01] input: done" in text and "[sub-02] input: done" in text
    assert (tmp_path / "run/sub-02/input/done.json").stat().st_mtime > released[0] - 1.0


def test_a_single_file_run_is_unchanged(tmp_path):
    [path] = _scans(tmp_path / "data", ("01",))
    results = run_pipeline(_cfg(tmp_path, str(path)))
    assert list(results) == ["subject"]
    assert (tmp_path / "run/subject/input/scan.nii.gz").is_file()
    assert _table(tmp_path)["subject"]["path"] == str(path)
    # one failing subject raises its own error, as before cohorts
    path.write_bytes(b"not a scan")
    with pytest.raises(StageError, match=r"^\[subject\] input: "):
        run_pipeline(_cfg(tmp_path, str(path)))


def _dask_cli(tmp_path, capsys, stages, workers="2"):
    toml = tmp_path / "cohort.toml"
    toml.write_text(f'out_dir = "{tmp_path / "run"}"\nstages = {json.dumps(stages)}\n'
                    f'[input]\nsource = "file"\npath = "{tmp_path}/data/sub-*/anat/*_T1w.nii.gz"\n')
    code = main(["run", str(toml), "--workers", workers])
    return code, capsys.readouterr()


def test_two_workers_run_the_subjects_as_dask_tasks(tmp_path, capsys):
    """Three subjects (one corrupt) on a 2-process LocalCluster through the CLI: the good ones
    finish, the corrupt one is recorded, the exit code says so; an in-process rerun skips."""
    _scans(tmp_path / "data", ("01", "02", "03"), corrupt=("03",))
    code, out = _dask_cli(tmp_path, capsys, ["input"])
    assert code == 2, out
    assert "1 of 3 subjects failed ([sub-03] input: " in out.err and "subjects.csv" in out.err
    assert "3 subjects as Dask tasks on tcp://" in out.out
    assert "[sub-01] input: running (no complete earlier run)" in out.out  # the worker's lines
    table = _table(tmp_path)
    assert [table[s]["status"] for s in ("sub-01", "sub-02", "sub-03")] == ["done", "done", "failed"]
    done = {s: json.loads((tmp_path / "run" / s / "input/done.json").read_text())
            for s in ("sub-01", "sub-02")}
    assert done["sub-01"]["outputs"]["scan.nii.gz"] != done["sub-02"]["outputs"]["scan.nii.gz"]
    lines = []
    cfg = load_config(tmp_path / "cohort.toml")
    with pytest.raises(StageError, match=r"\[sub-03\] input: "):
        run_pipeline(cfg, progress=lines.append)
    text = "\n".join(lines)
    assert "[sub-01] input: up to date" in text and "[sub-02] input: up to date" in text


@pytest.mark.slow
def test_dask_workers_and_the_serial_run_give_the_same_heads(tmp_path, capsys):
    """input, segment and layers of two subjects on two workers, then in this process into
    another folder: the same label maps (float64 on both sides; segmentation is deterministic)."""
    _scans(tmp_path / "data")
    stages = ["input", "segment", "layers"]
    code, out = _dask_cli(tmp_path, capsys, stages)
    assert code == 0, out.err
    cfg = dataclasses.replace(load_config(tmp_path / "cohort.toml"), out_dir=str(tmp_path / "serial"))
    run_pipeline(cfg)
    for sub in ("sub-01", "sub-02"):
        a = io.load_labels(tmp_path / "run" / sub / "segment/labels.nii.gz").labels
        b = io.load_labels(tmp_path / "serial" / sub / "segment/labels.nii.gz").labels
        assert np.array_equal(a, b), sub


def test_the_example_config_is_a_cohort_of_the_documented_layout(tmp_path, monkeypatch):
    """configs/cohort_example.toml's pattern picks the scans `jaxhead phantom` writes, not
    their label maps, and names the subjects by their folders."""
    cfg = load_config("configs/cohort_example.toml")
    monkeypatch.chdir(tmp_path)
    for s in (1, 2):
        assert main(["phantom", "--voxel-mm", "6", "--seed", str(s),
                     "--out", f"data/cohort/sub-0{s}/anat"]) == 0
    assert [(s.name, s.path) for s in subjects(cfg)] == [
        ("sub-01", "data/cohort/sub-01/anat/phantom_mri_seed1.nii.gz"),
        ("sub-02", "data/cohort/sub-02/anat/phantom_mri_seed2.nii.gz")]
