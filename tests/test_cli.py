"""The command line: phantom, info and a resumable run on a coarse phantom."""

import json

import pytest

from jaxhead.cli import main


def test_phantom_and_info(tmp_path, capsys):
    assert main(["phantom", "--modality", "ct", "--voxel-mm", "4", "--out", str(tmp_path)]) == 0
    scan = tmp_path / "phantom_ct_seed0.nii.gz"
    assert scan.exists() and (tmp_path / "phantom_ct_seed0_labels.nii.gz").exists()
    capsys.readouterr()
    assert main(["info", str(scan)]) == 0
    out = capsys.readouterr().out
    assert "RAS" in out and "4" in out


def test_run_resumes(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'name = "t"\nout_dir = "{tmp_path / "run"}"\nstages = ["input", "layers"]\n'
        '[input]\nmodalities = ["mri"]\nvoxel_mm = 3.0\n')
    assert main(["run", str(cfg)]) == 0
    assert (tmp_path / "run/mri/input/overlay.png").exists()
    assert (tmp_path / "run/mri/layers/layers.nii.gz").exists()
    summary = json.loads((tmp_path / "run/summary.json").read_text())
    assert set(summary["mri"]) == {"input", "layers"}
    capsys.readouterr()
    assert main(["run", str(cfg)]) == 0
    assert capsys.readouterr().out.count("up to date") == 2


def test_errors_are_reported_not_raised(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[inptu]\nseed = 1\n')
    assert main(["run", str(cfg)]) == 2
    assert "Did you mean `input`" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "missing.nii.gz")]) == 2
    with pytest.raises(SystemExit):
        main(["run"])
