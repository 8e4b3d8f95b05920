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
    page = tmp_path / "run/report.html"
    assert "data:image/png;base64," in page.read_text()  # the overlay and layers figures
    page.unlink()
    assert main(["report", str(cfg)]) == 0 and page.exists()


def test_errors_are_reported_not_raised(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[inptu]\nseed = 1\n')
    assert main(["run", str(cfg)]) == 2
    assert "Did you mean `input`" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "missing.nii.gz")]) == 2
    with pytest.raises(SystemExit):
        main(["run"])


def _config(tmp_path, text):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'out_dir = "{tmp_path / "run"}"\n' + text)
    return str(cfg)


def _one_line_error(capsys, argv, code=2):
    assert main(argv) == code
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    return err


def test_failures_are_one_line_with_exit_2(tmp_path, capsys):
    from test_run_errors import huge_voxel_nifti, singular_affine_nifti

    # A singular affine: `jaxhead info` describes the file, `jaxhead run` refuses it.
    sing = singular_affine_nifti(tmp_path / "sing.nii.gz")
    assert main(["info", str(sing)]) == 0 and "singular" in capsys.readouterr().out
    cfg = _config(tmp_path, f'stages = ["input"]\n[input]\nsource = "file"\npath = "{sing}"\n')
    err = _one_line_error(capsys, ["run", cfg])
    assert "[subject] input:" in err and "sing.nii.gz" in err and "singular" in err
    # A 4000 mm voxel size: refused with the memory estimate.
    big = huge_voxel_nifti(tmp_path / "big.nii.gz")
    cfg = _config(tmp_path, f'stages = ["input"]\n[input]\nsource = "file"\npath = "{big}"\n')
    assert "would need about" in _one_line_error(capsys, ["run", cfg])
    # An empty config (was: the whole default demo into runs/run) and `stages = []`.
    empty = tmp_path / "empty.toml"
    empty.write_text("# nothing yet\n")
    assert "config is empty" in _one_line_error(capsys, ["run", str(empty)])
    assert "`stages` is empty" in _one_line_error(capsys, ["run", _config(tmp_path, "stages = []\n")])
    # An unwritable run folder (was: a PermissionError traceback).
    (tmp_path / "afile").write_text("")
    cfg = _config(tmp_path, 'stages = ["input"]\n')
    err = _one_line_error(capsys, ["run", cfg, "--out", str(tmp_path / "afile/run")])
    assert "cannot write the run folder" in err and "afile/run" in err


def test_mesher_failure_is_one_line_and_debug_shows_the_traceback(tmp_path, capsys, monkeypatch):
    # Was: the CLI caught only ValueError/FileNotFoundError; fTetWild's RuntimeError was a
    # traceback.
    from jaxhead.run import stages

    def mesher(surfaces, cfg):
        raise RuntimeError("fTetWild failed on the skull surface: self-intersection.")

    monkeypatch.setattr(stages.io, "load_surface", lambda path, tissue: None)
    monkeypatch.setattr(stages, "tetrahedralize_reported", mesher)
    cfg = _config(tmp_path, 'stages = ["mesh"]\n[input]\nmodalities = ["mri"]\n'
                            '[electrodes]\nrefine_mesh = false\n')
    err = _one_line_error(capsys, ["run", cfg])
    assert err.startswith("jaxhead: error: [mri] mesh: the mesher failed on ") and "surfaces" in err
    assert "self-intersection" in err and "edge_mm" in err
    assert main(["--debug", "run", cfg]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "RuntimeError" in err


def test_a_bug_is_one_line_with_exit_1(tmp_path, capsys, monkeypatch):
    from jaxhead.run import stages

    def broken(cfg, subject):
        raise TypeError("unsupported operand")

    monkeypatch.setitem(stages.STAGES, "input", broken)
    cfg = _config(tmp_path, 'stages = ["input"]\n[input]\nmodalities = ["mri"]\n')
    err = _one_line_error(capsys, ["run", cfg], code=1)
    assert "internal error: TypeError: unsupported operand" in err and "--debug" in err


def test_a_locked_run_folder_is_refused(tmp_path, capsys):
    from jaxhead.run.lock import run_lock

    (tmp_path / "run").mkdir()
    cfg = _config(tmp_path, 'stages = ["input"]\n[input]\nmodalities = ["mri"]\n')
    with run_lock(tmp_path / "run"):
        err = _one_line_error(capsys, ["run", cfg])
    assert "is in use by jaxhead pid" in err and "--wait" in err
