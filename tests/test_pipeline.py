"""The pipeline runs stages in order, resumes finished ones and reruns what a change touches.

The stage functions here are cheap fakes with the real stages' declarations (`@stage`); the
cases of issue 14 ("a run you can trust") each have a test: a re-meshed head reruns the stages
reading the mesh, a missing or edited output reruns its stage, a failed stage leaves its previous
complete folder, a second process is refused or waits, a stale lock is taken over.
"""

import dataclasses
import json
import os
import secrets
import subprocess
import sys
import textwrap
import time

import pytest
from sphere_mesh import structured_sphere_mesh

from jaxhead import io
from jaxhead.run import RunLockedError, StageError, stage
from jaxhead.run import pipeline as pipeline_module
from jaxhead.run.config import InputConfig, InverseConfig, RunConfig
from jaxhead.run.lock import run_lock
from jaxhead.run.pipeline import run_pipeline
from jaxhead.run.stages import run_quality, run_segment
from jaxhead.segmentation.atlas import ATLAS_VERSION


def _fake_stages(calls, *, random_mesh=False):
    """input -> layers -> mesh -> forward, each writing a file that depends on what it read."""

    @stage(config=("input",))
    def run_input(cfg, subject):
        calls.append((subject.name, "input"))
        (subject.dir("input") / "scan.txt").write_text(f"scan seed {cfg.input.seed}")
        return {"stage": "input"}

    @stage(config=("layers",), reads=("input",))
    def run_layers(cfg, subject):
        calls.append((subject.name, "layers"))
        scan = subject.file("input", "scan.txt").read_text()
        (subject.dir("layers") / "layers.txt").write_text(f"layers of {scan}")
        return {"stage": "layers"}

    @stage(config=("mesh", "electrodes"), reads=("layers",))
    def run_mesh(cfg, subject):
        calls.append((subject.name, "mesh"))
        layers = subject.file("layers", "layers.txt").read_text()
        extra = secrets.token_hex(4) if random_mesh else ""  # fTetWild is not deterministic
        (subject.dir("mesh") / "mesh.vtu").write_text(f"mesh of {layers} {extra}")
        (subject.dir("mesh") / "mesh_cut.png").write_text("cut")
        return {"stage": "mesh"}

    @stage(config=("forward",), reads=("mesh",))
    def run_forward(cfg, subject):
        calls.append((subject.name, "forward"))
        mesh = subject.file("mesh", "mesh.vtu").read_text()
        (subject.dir("forward") / "voltages.csv").write_text(f"volts on {mesh}")
        return {"stage": "forward"}

    return {"input": run_input, "layers": run_layers, "mesh": run_mesh, "forward": run_forward}


def _cfg(tmp_path, **kw):
    return RunConfig(name="t", out_dir=str(tmp_path / "run"), input=InputConfig(modalities=("mri",)),
                     **kw)


def _run(cfg, stages, **kw):
    lines = []
    res = run_pipeline(cfg, stages=stages, progress=lines.append, report=False, **kw)
    return res, lines


def test_resume_and_force(tmp_path):
    cfg = _cfg(tmp_path)
    calls = []
    stages = _fake_stages(calls)
    res, _ = _run(cfg, stages)
    assert calls == [("mri", "input"), ("mri", "layers"), ("mri", "mesh"), ("mri", "forward")]
    assert res["mri"]["mesh"] == {"stage": "mesh"}
    done = json.loads((tmp_path / "run/mri/mesh/done.json").read_text())
    assert done["stage"] == "mesh" and done["seconds"] >= 0
    # done.json lists the outputs with their sha256 and the fingerprint's parts.
    assert set(done["outputs"]) == {"mesh.vtu", "mesh_cut.png"}
    assert all(len(d) == 64 for d in done["outputs"].values())
    assert set(done["fingerprint"]) == {"version", "config", "inputs", "files"}
    assert set(done["fingerprint"]["config"]) == {"mesh", "electrodes"}
    assert list(done["fingerprint"]["inputs"]) == ["layers/layers.txt"]
    calls.clear()
    _, lines = _run(cfg, stages)
    assert calls == [] and sum("up to date" in s for s in lines) == 4
    _, lines = _run(cfg, stages, force=True)
    assert len(calls) == 4 and all("(--force)" in s for s in lines if "running" in s)


def test_config_change_reruns_what_depends_on_it(tmp_path):
    cfg = _cfg(tmp_path)
    calls = []
    stages = _fake_stages(calls)
    _run(cfg, stages)
    calls.clear()
    cfg2 = dataclasses.replace(cfg, input=InputConfig(modalities=("mri",), seed=5))
    _, lines = _run(cfg2, stages)
    assert calls == [("mri", "input"), ("mri", "layers"), ("mri", "mesh"), ("mri", "forward")]
    assert any("input: running (config input.seed changed (0 -> 5))" in s for s in lines), lines
    assert any("layers: running (input input/scan.txt changed)" in s for s in lines), lines
    # The electrodes are part of the mesh stage's config (the mesh is refined under them).
    from jaxhead.electrodes import ElectrodeConfig

    calls.clear()
    _, lines = _run(dataclasses.replace(cfg2, electrodes=ElectrodeConfig(layout=16)), stages)
    assert calls == [("mri", "mesh")]  # same mesh content: forward stays up to date
    assert any("config electrodes.layout changed" in s for s in lines), lines


def test_remeshing_reruns_the_stages_that_read_the_mesh(tmp_path):
    # Issue 14: `stages = ["forward"]` after re-meshing said "up to date" and kept the voltages
    # of the old mesh: the fingerprint did not cover the files the stage reads.
    cfg = _cfg(tmp_path)
    calls = []
    stages = _fake_stages(calls, random_mesh=True)
    _run(cfg, stages)
    old_volts = (tmp_path / "run/mri/forward/voltages.csv").read_text()
    _run(dataclasses.replace(cfg, stages=("mesh",)), stages, force=True)  # a new mesh
    calls.clear()
    _, lines = _run(dataclasses.replace(cfg, stages=("forward",)), stages)
    assert calls == [("mri", "forward")]
    assert any("forward: running (input mesh/mesh.vtu changed)" in s for s in lines), lines
    new_volts = (tmp_path / "run/mri/forward/voltages.csv").read_text()
    assert new_volts != old_volts
    assert new_volts == "volts on " + (tmp_path / "run/mri/mesh/mesh.vtu").read_text()


def test_missing_or_edited_output_reruns_its_stage(tmp_path):
    # Issue 14: deleting surfaces/brain.stl or forward/voltages.csv of a finished run left every
    # stage "up to date", exit 0, the files still missing.
    cfg = _cfg(tmp_path)
    calls = []
    stages = _fake_stages(calls)
    _run(cfg, stages)
    (tmp_path / "run/mri/forward/voltages.csv").unlink()
    (tmp_path / "run/mri/mesh/mesh_cut.png").write_text("edited by hand")
    calls.clear()
    _, lines = _run(cfg, stages)
    assert calls == [("mri", "mesh"), ("mri", "forward")]
    assert any("mesh: running (output mesh_cut.png changed)" in s for s in lines), lines
    assert any("forward: running (output voltages.csv missing)" in s for s in lines), lines
    assert (tmp_path / "run/mri/forward/voltages.csv").exists()
    # A done.json that is not ours (an older jaxhead) reruns too.
    (tmp_path / "run/mri/input/done.json").write_text('{"hash": "abc"}')
    calls.clear()
    _, lines = _run(cfg, stages)
    assert calls == [("mri", "input")] and any("older jaxhead" in s for s in lines), lines


def test_version_and_named_files_are_in_the_fingerprint(tmp_path, monkeypatch):
    cfg = _cfg(tmp_path)
    calls = []
    stages = _fake_stages(calls)
    _run(cfg, stages)
    monkeypatch.setattr(pipeline_module, "package_version", lambda: "9.9.9")
    calls.clear()
    _, lines = _run(cfg, stages)
    assert len(calls) == 4 and any("jaxhead version" in s and "9.9.9" in s for s in lines), lines
    # Files named by config keys (`*_path`, `*_mesh`: approx_error_mesh was missed) enter by content.
    fine = tmp_path / "fine.vtu"
    fine.write_text("fine mesh 1")

    @stage(config=("inverse",), reads=("mesh",))
    def run_inverse(cfg, subject):
        calls.append((subject.name, "inverse"))
        (subject.dir("inverse") / "fit.txt").write_text("fit")
        return {}

    stages = {**stages, "inverse": run_inverse}
    cfg = dataclasses.replace(cfg, inverse=InverseConfig(approx_error_mesh=str(fine)))
    _run(cfg, stages)
    fine.write_text("fine mesh 2")
    calls.clear()
    _, lines = _run(cfg, stages)
    assert calls == [("mri", "inverse")]
    assert any("inverse: running (file" in s and "fine.vtu changed" in s for s in lines), lines


def test_a_stage_may_read_only_what_it_declares(tmp_path):
    @stage(config=("input",))
    def sneaky(cfg, subject):
        subject.file("layers", "layers.txt")
        return {}

    stages = {**_fake_stages([]), "forward": sneaky}
    with pytest.raises(RuntimeError, match="declares reading only"):
        _run(_cfg(tmp_path), stages)


def test_a_failed_stage_leaves_its_previous_complete_folder(tmp_path):
    # Issue 14: a stage failing (or killed) while writing left new and old files side by side.
    cfg = _cfg(tmp_path)
    calls = []
    stages = _fake_stages(calls)
    _run(cfg, stages)
    before = {p.name: p.read_bytes() for p in (tmp_path / "run/mri/mesh").iterdir()}

    @stage(config=("mesh", "electrodes"), reads=("layers",))
    def half_mesh(cfg, subject):
        (subject.dir("mesh") / "mesh.vtu").write_text("a new mesh")
        raise ValueError("the mesher gave up")

    cfg2 = dataclasses.replace(cfg, input=InputConfig(modalities=("mri",), seed=7))
    with pytest.raises(StageError, match=r"\[mri\] mesh: the mesher gave up"):
        _run(cfg2, {**stages, "mesh": half_mesh})
    after = {p.name: p.read_bytes() for p in (tmp_path / "run/mri/mesh").iterdir()}
    assert after == before  # old mesh.vtu, old mesh_cut.png, old done.json: no mix
    assert not [p for p in (tmp_path / "run/mri").iterdir() if p.name.startswith(".")]
    calls.clear()
    _, lines = _run(cfg2, stages)  # the next run redoes it, saying why
    assert ("mri", "mesh") in calls and any("mesh: running (input layers/layers.txt" in s
                                            for s in lines), lines


_KILL_SCRIPT = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from jaxhead.run import stage
    from jaxhead.run.config import InputConfig, RunConfig
    from jaxhead.run.pipeline import run_pipeline

    @stage(config=("input",))
    def run_input(cfg, subject):
        out = subject.dir("input")
        (out / "a.txt").write_text(f"a {cfg.input.seed}")
        if cfg.input.seed == 1:
            (out / "b.txt").write_text("b half")
            Path(sys.argv[2]).write_text("writing")
            time.sleep(60)  # killed here
        (out / "b.txt").write_text(f"b {cfg.input.seed}")
        return {}

    cfg = RunConfig(out_dir=sys.argv[1], input=InputConfig(modalities=("mri",), seed=int(sys.argv[3])))
    run_pipeline(cfg, stages={"input": run_input}, report=False)
""")


def _spawn(tmp_path, seed, flag):
    script = tmp_path / "kill_me.py"
    script.write_text(_KILL_SCRIPT)
    env = {**os.environ, "PYTHONPATH": os.getcwd()}
    return subprocess.Popen([sys.executable, str(script), str(tmp_path / "run"), str(flag),
                             str(seed)], env=env, stderr=subprocess.PIPE, text=True)


def _wait_for(path, proc, timeout_s=60.0):
    t0 = time.monotonic()
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"the child exited early: {proc.stderr.read()}")
        assert time.monotonic() - t0 < timeout_s
        time.sleep(0.05)


def test_kill_9_mid_stage_leaves_the_previous_folder_and_the_lock_is_taken_over(tmp_path):
    flag = tmp_path / "flag"
    assert _spawn(tmp_path, 0, flag).wait(120) == 0
    folder = tmp_path / "run/mri/input"
    before = {p.name: p.read_text() for p in folder.iterdir()}
    assert before["b.txt"] == "b 0"
    child = _spawn(tmp_path, 1, flag)
    _wait_for(flag, child)
    # While it runs, the folder is locked: a second run is refused with who holds it.
    with pytest.raises(RunLockedError, match=f"pid {child.pid}.*--wait"):
        with run_lock(tmp_path / "run"):
            pass
    child.kill()  # SIGKILL mid-write
    child.wait()
    assert {p.name: p.read_text() for p in folder.iterdir()} == before
    leftovers = [p.name for p in (tmp_path / "run/mri").iterdir() if p.name.startswith(".")]
    assert len(leftovers) == 1 and ".input.tmp-" in leftovers[0]
    lines = []
    with run_lock(tmp_path / "run", say=lines.append):  # the dead holder's lock is free
        pass
    assert any(f"stale lock of jaxhead pid {child.pid}" in s for s in lines), lines
    flag.unlink()
    assert _spawn(tmp_path, 2, flag).wait(120) == 0
    assert {p.name: p.read_text() for p in folder.iterdir() if p.suffix == ".txt"} == {
        "a.txt": "a 2", "b.txt": "b 2"}
    assert not [p for p in (tmp_path / "run/mri").iterdir() if p.name.startswith(".")]


def test_killed_between_the_two_renames_restores_the_previous_folder(tmp_path):
    cfg = _cfg(tmp_path)
    calls = []
    stages = _fake_stages(calls)
    _run(cfg, stages)
    mri = tmp_path / "run/mri"
    os.rename(mri / "mesh", mri / ".mesh.old-1234abcd")  # as if killed right after this rename
    calls.clear()
    _, lines = _run(cfg, stages)
    assert calls == [] and any("restored mesh/" in s for s in lines), lines


def test_a_second_process_is_refused_or_waits(tmp_path):
    # Issue 14: two `jaxhead run` on one folder both wrote it.
    (tmp_path / "run").mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            from jaxhead.run.lock import run_lock
            with run_lock({str(tmp_path / "run")!r}):
                print("locked", flush=True)
                time.sleep(1.5)
        """)], stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": os.getcwd()})
    assert holder.stdout.readline().strip() == "locked"
    cfg = _cfg(tmp_path)
    with pytest.raises(RunLockedError, match=f"in use by jaxhead pid {holder.pid}"):
        _run(cfg, _fake_stages([]))
    t0 = time.monotonic()
    res, lines = _run(cfg, _fake_stages([]), wait=True)
    assert time.monotonic() - t0 > 0.2 and "forward" in res["mri"]
    assert any("waiting for it to finish" in s for s in lines), lines
    assert holder.wait(30) == 0


def test_empty_stages_and_unwritable_folders_are_errors(tmp_path, monkeypatch):
    # Issue 14: `stages = []` exited 0 having done nothing.
    with pytest.raises(ValueError, match="`stages` is empty"):
        RunConfig(stages=())
    cfg = RunConfig(out_dir=str(tmp_path), stages=("input", "mesh", "layers"))
    with pytest.raises(ValueError, match="pipeline order"):
        _run(cfg, _fake_stages([]))
    cfg = RunConfig(out_dir=str(tmp_path), stages=("input", "mesher"))
    with pytest.raises(ValueError, match="unknown stage"):
        _run(cfg, _fake_stages([]))
    # Issue 14: an unwritable run folder was a PermissionError traceback.
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="cannot write the run folder .*file/run.*out_dir"):
        _run(RunConfig(out_dir=str(tmp_path / "file/run")), _fake_stages([]))

    def denied(self, *a, **k):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(pipeline_module.Path, "mkdir", denied)
    with pytest.raises(ValueError, match="Permission denied.*--out"):
        _run(RunConfig(out_dir=str(tmp_path / "ro/run")), _fake_stages([]))


def test_os_errors_in_a_stage_name_the_file(tmp_path):
    @stage(config=("input",))
    def unwritable(cfg, subject):
        raise PermissionError(13, "Permission denied", str(subject.dir("input") / "scan.nii.gz"))

    with pytest.raises(StageError, match=r"\[mri\] input: Permission denied: .*scan.nii.gz"):
        _run(_cfg(tmp_path), {"input": unwritable})


def test_what_the_library_logs_is_kept_in_the_stage_folder(tmp_path):
    # STYLE.md: a repair (relabelled voxels, a repaired surface) is logged at INFO and shown in
    # the run's report; the stage's log.txt is one of its outputs.
    import logging

    @stage(config=("input",))
    def repairing(cfg, subject):
        logging.getLogger("jaxhead.phantom").info("5870 voxels relabelled to their enclosing tissue")
        logging.getLogger("jaxhead.phantom").debug("not kept")
        (subject.dir("input") / "scan.txt").write_text("scan")
        return {}

    _run(_cfg(tmp_path), {"input": repairing})
    text = (tmp_path / "run/mri/input/log.txt").read_text()
    assert text == "INFO jaxhead.phantom: 5870 voxels relabelled to their enclosing tissue\n"
    done = json.loads((tmp_path / "run/mri/input/done.json").read_text())
    assert "log.txt" in done["outputs"]
    assert logging.getLogger("jaxhead").level == logging.NOTSET  # restored


def test_quality_stage_names_the_histograms_it_leaves(tmp_path):
    # The stage writes into a staging folder renamed on success; table2.txt and report.json
    # named the staging folder's PNGs (gone after the rename) until they named them relative
    # to the quality folder.
    @stage(config=("mesh",))
    def run_mesh(cfg, subject):
        io.save_mesh(structured_sphere_mesh(h_mm=18.0), subject.dir("mesh") / "mesh.vtu")
        return {}

    _run(_cfg(tmp_path), {"mesh": run_mesh, "quality": run_quality})
    folder = tmp_path / "run/mri/quality"
    named = json.loads((folder / "report.json").read_text())["png_paths"]
    assert len(named) == 7 and all((folder / p).is_file() for p in named), named
    table = (folder / "table2.txt").read_text()
    assert "Histograms: " + ", ".join(named) in table and ".tmp" not in table


def test_a_declared_data_version_is_in_the_fingerprint(tmp_path):
    # The segment stage builds (and caches outside the run folder) the default atlas: a new atlas
    # recipe (ATLAS_VERSION) must rerun it on resume, where the package version stays the same.
    cfg = _cfg(tmp_path)
    calls = []
    version = {"atlas": 1}

    def make():
        @stage(config=("input",), versions=dict(version))
        def run_input(cfg, subject):
            calls.append((subject.name, "input"))
            (subject.dir("input") / "scan.txt").write_text("scan")
            return {}
        return {**_fake_stages(calls), "input": run_input}

    _run(cfg, make())
    calls.clear()
    _run(cfg, make())
    assert ("mri", "input") not in calls  # same version: up to date
    version["atlas"] = 2
    _, lines = _run(cfg, make())
    assert ("mri", "input") in calls and any("data version atlas changed" in s for s in lines), lines


def test_the_segment_stage_declares_the_atlas_version():
    assert dict(run_segment.stage_spec.versions) == {"atlas": ATLAS_VERSION}
