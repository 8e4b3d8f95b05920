"""The study engine end to end on a small sphere mesh (2 worker processes), reruns, bad input."""

import csv
import json

import numpy as np
import pytest
from sphere_mesh import structured_sphere_mesh

from jaxhead.io import save_mesh
from jaxhead.study import (
    COLUMNS,
    expand_samples,
    finished_samples,
    load_study_config,
    run_study,
    study_config_from_dict,
)

TOML = """
[study]
name = "sphere"
out_dir = "{out}"
seed = 3

[study.reference]
source = "mesh"
mesh_path = "{mesh}"
n_elec = 8
electrode_radius_mm = 12.0
current_a = 1e-3

[study.measures]
cell_mm = 20.0

[[study.perturbations]]
kind = "grf"
tissue = "csf"
amplitude = 0.3
correlation_mm = 30.0
samples = 2

[[study.perturbations]]
kind = "grf"
tissue = "brain"
amplitude = 6.0      # more than the 4 mm CSF: inverts tets, a recorded failure
correlation_mm = 40.0
samples = 1

[[study.perturbations]]
kind = "electrode_position"
amplitude = 2.0
samples = 1
"""


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("study")
    mesh = structured_sphere_mesh(h_mm=16.0)
    save_mesh(mesh, tmp / "sphere.vtu")
    cfg = tmp / "study.toml"
    cfg.write_text(TOML.format(out=tmp / "run", mesh=tmp / "sphere.vtu"))
    out = run_study(cfg, workers=2, progress=False)
    return cfg, out


def read(out):
    with open(out / "samples.csv") as f:
        return list(csv.DictReader(f))


def test_outputs(study):
    cfg, out = study
    rows = read(study[1])
    assert len(rows) == 4 and list(rows[0]) == list(COLUMNS)
    grf = [r for r in rows if r["perturbation"] == "grf" and r["tissue"] == "csf"]
    assert all(not r["error"] for r in grf), grf
    for r in grf:
        assert float(r["rel_voltage_change"]) > 0 and r["route"] == "morph"
        # at sd 0.3 mm the first-order prediction is within 10 % per sample
        assert float(r["linearisation_error"]) < 0.10
        assert np.isfinite(float(r["sigma_bias_percent_skull"]))
    bad = [r for r in rows if r["tissue"] == "brain"][0]
    assert bad["error"].startswith("MorphError") and int(bad["n_inverted"]) > 0
    el = [r for r in rows if r["perturbation"] == "electrode_position"][0]
    assert not el["error"] and float(el["rel_voltage_change"]) > 0
    s = json.loads((out / "summary.json").read_text())
    g = [g for g in s["groups"] if g["tissue"] == "csf"][0]
    assert g["first_order"]["agree_within_10_percent"] is True
    a = s["agreement"]  # the bar's statement: measure, threshold, the sd <= 0.5 mm groups
    assert a["bar"] == 0.10 and "||dV - S d|| / ||dV||" in a["measure"] and a["met"] is True
    assert [(x["tissue"], x["sd_mm"], x["n"]) for x in a["groups"]] == [("csf", 0.3, 2)]
    assert a["max"] == pytest.approx(g["first_order"]["per_sample_linearisation_error_max"])
    # second order per sample, and the distribution the first-order route predicts
    i = COLUMNS.index("first_order_rel_error")
    assert COLUMNS[i + 1] == "second_order_rel_error" and i > COLUMNS.index("description")
    e1 = np.array([float(r["first_order_rel_error"]) for r in grf])
    e2 = np.array([float(r["second_order_rel_error"]) for r in grf])
    np.testing.assert_array_equal(e1, [float(r["linearisation_error"]) for r in grf])
    print("engine first/second order errors", e1, e2)
    assert np.all(e2 < 0.2 * e1)  # the remainder after second order is third order
    a2 = a["second_order"]
    assert a2["max"] == pytest.approx(e2.max()) and a2["mean"] == pytest.approx(e2.mean())
    assert a2["within_bar"] is True and a2["seconds_per_sample"] > 0
    dist = a["distribution"]["groups"]
    assert [(x["tissue"], x["sd_mm"], x["n"]) for x in dist] == [("csf", 0.3, 2)]
    rel = np.array([float(r["rel_voltage_change"]) for r in grf])
    assert dist[0]["sampled_rms"] == pytest.approx(np.sqrt(np.mean(rel**2)))
    assert dist[0]["ratio"] == pytest.approx(dist[0]["sampled_rms"] / dist[0]["first_order_rms"])
    assert 0 < dist[0]["ratio_sampling_sd"] <= np.sqrt(1 / (2 * 2))  # n = 2, dof >= 1
    assert g["n"] == 2 and g["n_failed"] == 0
    assert (out / "first_order" / "sensitivity_csf.vtu").is_file()
    assert (out / "first_order" / "sensitivity_csf.png").is_file()
    assert (out / "distributions.png").is_file()


def test_rerun_runs_only_missing_samples(study):
    cfg, out = study
    before = read(out)
    victim, *others = sorted((out / "samples").glob("*.json"))
    victim.unlink()
    kept = {f.name: f.stat().st_mtime_ns for f in others}
    run_study(cfg, workers=1, progress=False)
    s = json.loads((out / "summary.json").read_text())
    assert s["run"]["ran"] == 1 and s["run"]["skipped_finished"] == 3
    assert victim.is_file()
    assert {f.name: f.stat().st_mtime_ns for f in others} == kept  # not recomputed
    after = read(out)
    for a, b in zip(before, after):  # seeded: the rerun sample is the same sample
        assert a["rel_voltage_change"] == pytest.approx(b["rel_voltage_change"]) or a["error"]


def test_a_changed_parameter_reruns_only_its_samples(study):
    """Never stale: after an edit of one perturbation's parameter, a rerun runs that
    perturbation's samples (and the first-order task) again and keeps the others' files."""
    cfg, out = study
    edited = cfg.with_name("edited.toml")
    edited.write_text(cfg.read_text().replace("correlation_mm = 30.0", "correlation_mm = 25.0"))
    files = sorted((out / "samples").glob("*.json"))
    others = {f.name: f.stat().st_mtime_ns for f in files if "-grf-csf-" not in f.name}
    assert len(others) == 2
    run_study(edited, workers=1, progress=False)
    s = json.loads((out / "summary.json").read_text())
    assert s["run"]["ran"] == 2 and s["run"]["stale_rerun"] == 2
    assert s["run"]["skipped_finished"] == 2
    assert {f.name: f.stat().st_mtime_ns for f in files if f.name in others} == others
    rows = [r for r in read(out) if r["tissue"] == "csf"]
    assert {float(r["correlation_mm"]) for r in rows} == {25.0}
    fo = json.loads((out / "first_order" / "first_order.json").read_text())
    assert {p["correlation_mm"] for p in fo["predictions"] if p["tissue"] == "csf"} == {25.0}


def test_sample_keys_follow_what_a_sample_depends_on():
    def keys(**kw):
        d = {"seed": 1, "perturbations": [
            {"kind": "grf", "tissue": "csf", "amplitude": 0.5, "samples": 2,
             "correlation_mm": kw.pop("corr", 20.0)},
            {"kind": "dilate", "tissue": "skull", "amplitude": 1, "samples": kw.pop("n", 1)}],
            **kw}
        return [s["key"] for s in expand_samples(study_config_from_dict(d))]

    k = keys()
    assert len(set(k)) == 3
    assert keys(n=3)[:3] == k  # more samples: the finished ones stay valid
    assert keys(corr=25.0)[:2] != k[:2] and keys(corr=25.0)[2] == k[2]
    assert set(keys(measures={"noise_percent": 1.0})).isdisjoint(k)
    assert set(keys(reference={"n_elec": 8})).isdisjoint(k)


def test_finished_samples_reuses_only_matching_keys(tmp_path):
    samples = [{"sample": f"000{i}", "key": f"k{i}"} for i in range(4)]
    for i, (key, err) in enumerate([("k0", ""), ("old", ""), ("k2", "ValueError: x")]):
        (tmp_path / f"000{i}.json").write_text(json.dumps({"sample": f"000{i}", "key": key,
                                                           "error": err}))
    done, stale = finished_samples(samples, tmp_path)
    assert sorted(done) == ["0000", "0002"] and stale == 1
    done, stale = finished_samples(samples, tmp_path, retry_failed=True)
    assert sorted(done) == ["0000"] and stale == 1
    (tmp_path / "0000.json").write_text(json.dumps({"sample": "0000"}))  # written with no key
    assert "0000" not in finished_samples(samples, tmp_path)[0]


def base(**pert):
    return {"reference": {"source": "mesh", "mesh_path": "x.vtu"},
            "perturbations": [{"kind": "grf", "tissue": "csf", "amplitude": 0.5, **pert}]}


@pytest.mark.parametrize("pert, match", [
    ({"kind": "gfr"}, "unknown kind 'gfr'.*did you mean 'grf'"),
    ({"tissue": "bone"}, "unknown tissue 'bone'"),
    ({"amplitude": -0.5}, "amplitude = -0.5.*>= 0"),
    ({"route": "remesh"}, "realised by \\['morph'\\]"),
    ({"samples": 0}, "samples = 0"),
])
def test_bad_perturbations_are_one_clear_error(pert, match):
    with pytest.raises(ValueError, match=match):
        study_config_from_dict(base(**pert))


def test_unknown_keys_and_remesh_without_labels(tmp_path):
    with pytest.raises(ValueError, match=r"unknown key `sampels` in \[study.perturbations\[0\]\]. Did you mean `samples`"):
        study_config_from_dict({"perturbations": [{"kind": "grf", "tissue": "csf",
                                                   "amplitude": 1, "sampels": 2}]})
    d = base()
    d["perturbations"].append({"kind": "dilate", "tissue": "csf", "amplitude": 1})
    with pytest.raises(ValueError, match="re-mesh route"):
        study_config_from_dict(d)
    p = tmp_path / "x.toml"
    p.write_text("[studdy]\n")
    with pytest.raises(ValueError, match="no \\[study\\] section"):
        load_study_config(p)


def test_unreachable_scheduler_fails_before_any_work(tmp_path):
    d = base()
    d["out_dir"] = str(tmp_path / "run")
    save_mesh(structured_sphere_mesh(h_mm=32.0), tmp_path / "x.vtu")
    d["reference"]["mesh_path"] = str(tmp_path / "x.vtu")
    cfg = study_config_from_dict(d)
    with pytest.raises(ValueError, match="cannot reach the Dask scheduler"):
        run_study(cfg, scheduler="tcp://127.0.0.1:9", progress=False)
    assert not (tmp_path / "run" / "study" / "samples").exists()


def test_sample_seeds_are_distinct_and_stable():
    cfg = study_config_from_dict({"seed": 1, "perturbations": [
        {"kind": "grf", "tissue": "csf", "amplitude": 0.5, "samples": 3},
        {"kind": "dilate", "tissue": "skull", "amplitude": 1, "samples": 2}]})
    a, b = expand_samples(cfg), expand_samples(cfg)
    assert a == b and len({s["seed"] for s in a}) == 5
    assert [s["route"] for s in a] == ["morph"] * 3 + ["remesh"] * 2


def test_shipped_configs_load():
    import pathlib

    root = pathlib.Path(__file__).parent.parent / "configs"
    quick = load_study_config(root / "study_quick.toml")
    kinds = {p.kind for p in quick.perturbations}
    routes = {p.realised_by for p in quick.perturbations}
    assert len(expand_samples(quick)) == 4 and len(kinds) == 2 and routes == {"morph", "remesh"}
    assert quick.reference.voxel_mm == 4.0
    full = load_study_config(root / "segmentation_sensitivity.toml")
    assert {p.realised_by for p in full.perturbations} == {"morph", "remesh", "electrodes"}


@pytest.mark.parametrize("pert, argv, match", [
    ({"kind": "grf", "tissue": "csf", "amplitude": -1.0}, [], "amplitude = -1.0"),
    ({"kind": "dilate", "tissue": "bone", "amplitude": 1}, [], "unknown tissue 'bone'"),
    ({"kind": "skull_hol", "amplitude": 8.0}, [], "unknown kind 'skull_hol'.*did you mean"),
    ({"kind": "grf", "tissue": "csf", "amplitude": 0.5}, ["--scheduler", "tcp://127.0.0.1:9"],
     "cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'"),
])
def test_cli_bad_input_is_one_line_before_any_work(tmp_path, capsys, pert, argv, match):
    """`jaxhead study`: exit 2, one line naming the value, and no study folder written."""
    import re

    from jaxhead.cli import main

    mesh = structured_sphere_mesh(h_mm=32.0)
    save_mesh(mesh, tmp_path / "m.vtu")
    cfg = tmp_path / "s.toml"
    cfg.write_text(f'[study]\nout_dir = "{tmp_path / "run"}"\n[study.reference]\nsource = "mesh"\n'
                   f'mesh_path = "{tmp_path / "m.vtu"}"\n[[study.perturbations]]\n'
                   + "".join(f"{k} = {json.dumps(v)}\n" for k, v in pert.items()))
    assert main(["study", str(cfg), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("jaxhead: error:"), err
    assert re.search(match, err), err
    assert not (tmp_path / "run").exists()


def test_missing_reference_file_fails_before_any_work(tmp_path):
    d = base()
    d["out_dir"] = str(tmp_path / "run")
    d["reference"]["mesh_path"] = str(tmp_path / "nope.vtu")
    with pytest.raises(ValueError, match="mesh_path = .*nope.vtu' does not exist"):
        run_study(study_config_from_dict(d), workers=1, progress=False)
    assert not (tmp_path / "run").exists()
