"""The pipeline runs stages in order, resumes finished ones and reruns what a config change touches."""

import dataclasses
import json

import pytest

from jaxhead.run.config import InputConfig, RunConfig
from jaxhead.run.pipeline import run_pipeline


def _fake_stages(calls):
    def make(name):
        def fn(cfg, subject):
            calls.append((subject.name, name))
            (subject.dir(name) / "out.txt").write_text(name)
            return {"stage": name}
        return fn
    return {"input": make("input"), "layers": make("layers"), "mesh": make("mesh")}


def test_resume_and_force(tmp_path):
    cfg = RunConfig(name="t", out_dir=str(tmp_path / "run"), input=InputConfig(modalities=("mri",)))
    calls = []
    stages = _fake_stages(calls)
    res = run_pipeline(cfg, stages=stages, progress=lambda s: None)
    assert calls == [("mri", "input"), ("mri", "layers"), ("mri", "mesh")]
    assert res["mri"]["mesh"] == {"stage": "mesh"}
    done = json.loads((tmp_path / "run/mri/mesh/done.json").read_text())
    assert done["stage"] == "mesh" and done["seconds"] >= 0
    calls.clear()
    run_pipeline(cfg, stages=stages, progress=lambda s: None)
    assert calls == []  # everything up to date
    run_pipeline(cfg, stages=stages, force=True, progress=lambda s: None)
    assert len(calls) == 3


def test_config_change_reruns_from_that_stage(tmp_path):
    cfg = RunConfig(name="t", out_dir=str(tmp_path / "run"), input=InputConfig(modalities=("mri",)))
    calls = []
    stages = _fake_stages(calls)
    run_pipeline(cfg, stages=stages, progress=lambda s: None)
    calls.clear()
    cfg2 = dataclasses.replace(cfg, input=InputConfig(modalities=("mri",), seed=5))
    run_pipeline(cfg2, stages=stages, progress=lambda s: None)
    assert calls == [("mri", "input"), ("mri", "layers"), ("mri", "mesh")]
    # A failed stage leaves no marker, so the next run redoes it.
    calls.clear()

    def boom(cfg, subject):
        raise RuntimeError("stage failed")

    with pytest.raises(RuntimeError):
        run_pipeline(dataclasses.replace(cfg2, input=InputConfig(modalities=("mri",), seed=6)),
                     stages={**stages, "layers": boom}, progress=lambda s: None)
    assert not (tmp_path / "run/mri/layers/done.json").exists()


def test_stage_names_checked(tmp_path):
    cfg = RunConfig(out_dir=str(tmp_path), stages=("input", "mesh", "layers"))
    with pytest.raises(ValueError, match="pipeline order"):
        run_pipeline(cfg, stages=_fake_stages([]), progress=lambda s: None)
    cfg = RunConfig(out_dir=str(tmp_path), stages=("input", "mesher"))
    with pytest.raises(ValueError, match="unknown stage"):
        run_pipeline(cfg, stages=_fake_stages([]), progress=lambda s: None)


def test_electrode_change_reruns_the_mesh_stage(tmp_path):
    # The mesh is refined under the electrodes: [electrodes] is part of the mesh stage's hash.
    from jaxhead.electrodes import ElectrodeConfig

    cfg = RunConfig(name="t", out_dir=str(tmp_path / "run"), input=InputConfig(modalities=("mri",)))
    calls = []
    stages = _fake_stages(calls)
    run_pipeline(cfg, stages=stages, progress=lambda s: None)
    calls.clear()
    run_pipeline(dataclasses.replace(cfg, electrodes=ElectrodeConfig(layout=16)), stages=stages,
                 progress=lambda s: None)
    assert calls == [("mri", "mesh")]
