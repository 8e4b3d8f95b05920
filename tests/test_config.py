"""TOML configs: loading, typo suggestions, type errors."""

import pytest

from jaxhead.run.config import InputConfig, RunConfig, load_config


def _write(tmp_path, text):
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


def test_demo_config_loads():
    cfg = load_config("configs/demo.toml")
    assert isinstance(cfg, RunConfig)
    assert cfg.input.source == "phantom"
    assert cfg.input.modalities == ("mri", "ct")


def test_typo_is_caught_with_suggestion(tmp_path):
    p = _write(tmp_path, '[input]\nmodalites = ["mri"]\n')
    with pytest.raises(ValueError, match="Did you mean `modalities`"):
        load_config(p)
    p = _write(tmp_path, 'nmae = "x"\n')
    with pytest.raises(ValueError, match="Did you mean `name`"):
        load_config(p)


def test_wrong_types_and_choices(tmp_path):
    with pytest.raises(ValueError, match="choose one of"):
        load_config(_write(tmp_path, '[input]\nsource = "dicom"\n'))
    with pytest.raises(ValueError, match="must be a number"):
        load_config(_write(tmp_path, '[input]\nvoxel_mm = "two"\n'))
    with pytest.raises(ValueError, match="needs `path`"):
        load_config(_write(tmp_path, '[input]\nsource = "file"\n'))
    with pytest.raises(ValueError, match="not valid TOML"):
        load_config(_write(tmp_path, "[input\n"))
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        load_config(tmp_path / "nope.toml")


def test_frozen():
    cfg = InputConfig()
    with pytest.raises(Exception):
        cfg.seed = 3


def test_recording_and_mesh_keys_load_from_toml(tmp_path):
    (tmp_path / "rec.json").write_text('{"Freq": [10]}')
    (tmp_path / "rec.mat").write_bytes(b"")
    (tmp_path / "head.msh").write_text("")
    cfg = load_config(_write(tmp_path, f"""
[input]
source = "mesh"
mesh_path = "{tmp_path / 'head.msh'}"
tissue_map = {{ "1" = "brain", "2" = "brain", "3" = "csf", "4" = "skull", "5" = "scalp" }}
facing = "reorient"

[inverse]
measured_path = "{tmp_path / 'rec.json'}"
frequency_hz = "all"
fit_priors = {{ csf = [1.79, 0.02] }}
fit_tissues = ["brain", "csf", "skull", "scalp"]
fit_reject_sigma = 0
"""))
    assert cfg.input.mesh_tissue_map() == {1: "brain", 2: "brain", 3: "csf", 4: "skull",
                                           5: "scalp"}
    c = cfg.inverse
    assert c.measured_format == "ucl" and c.frequency_hz == "all"
    # the .mat beside the JSON is named, so the resume fingerprint (files named *_path) covers it
    assert c.measured_voltages_path == str(tmp_path / "rec.mat")
    assert c.fit_priors == {"csf": (1.79, 0.02)} and c.fit_reject_sigma == 0.0
    cfg = load_config(_write(tmp_path, f'[inverse]\nmeasured_path = "{tmp_path / "rec.json"}"\n'
                                       "frequency_hz = [10, 20.5]\n"))
    assert cfg.inverse.frequency_hz == (10.0, 20.5)


@pytest.mark.parametrize("section,text,match", [
    ("input", 'source = "mesh"', r"source = \"mesh\" needs `mesh_path`"),
    ("input", 'source = "mesh"\nmesh_path = "nope.msh"', r"`mesh_path` = 'nope.msh' is not a file"),
    ("input", 'mesh_path = "{head}"', r"`mesh_path` = .* is set but source = 'phantom'.*source = \"mesh\""),
    ("input", 'source = "mesh"\nmesh_path = "{head}"\ntissue_map = "freesurfer"',
     r"`input.tissue_map` = 'freesurfer'; choose one of \['simnibs'\]"),
    ("input", 'source = "mesh"\nmesh_path = "{head}"\ntissue_map = {{ "1" = "bone" }}',
     r"`tissue_map.1` = 'bone'; use one of"),
    ("input", 'source = "mesh"\nmesh_path = "{head}"\nmesh_units = "inch"', r"mesh_units.*choose one of"),
    ("input", 'facing = "reorient"', r"apply to a mesh file; set source = \"mesh\""),
    ("inverse", 'frequency_hz = 10', r"`frequency_hz` describe a recording, but `measured_path` is not set"),
    ("inverse", 'measured_path = "{rec}"\nfrequency_hz = -5', r"`frequency_hz` = -5.0; frequencies must be > 0"),
    ("inverse", 'measured_path = "{rec}"\nfrequency_hz = "most"', r"frequency_hz.*does not fit"),
    ("inverse", 'measured_path = "{rec}"\nmeasured_format = "edf"', r"measured_format.*choose one of"),
    ("inverse", 'measured_path = "{rec}"\nmeasured_voltages_path = "nope.mat"',
     r"`measured_voltages_path` = 'nope.mat' is not a file"),
    ("inverse", 'measured_path = "{rec}"\nmeasured_current_a = -1e-4', r"`measured_current_a` must be > 0"),
    ("inverse", 'measured_path = "{volts}"\nfrequency_hz = 10',
     r"`frequency_hz` need a recording layout, but `measured_format` is \"voltages\""),
    ("inverse", 'fit_tissues = ["brain", "bone"]', r"`fit_tissues` = \('brain', 'bone'\); list distinct"),
    ("inverse", 'fit_contact_prior = 0.5', r"`fit_contact_prior` = 0.5 .*factor > 1"),
    ("inverse", 'fit_priors = {{ skull = [0.01] }}', r"fit_priors.skull.*needs 2 entries"),
    ("inverse", 'fit_priors = {{ skull = [0.01, -1] }}', r"`fit_priors.skull` = \[0.01, -1.0\]; give \[value"),
    ("inverse", 'fit_priors = {{ bone = [1, 0.1] }}', r"`fit_priors.bone`: priors are for"),
    ("inverse", 'fit_tissues = ["brain"]\nfit_priors = {{ csf = [1.79, 0.02] }}',
     r"`fit_priors.csf`: csf is not in `fit_tissues`"),
    ("inverse", 'fit_loss = "tukey"', r"fit_loss.*choose one of"),
    ("inverse", 'fit_loss_scale = 0', r"`fit_loss_scale` must be > 0"),
    ("inverse", 'fit_reject_sigma = -1', r"`fit_reject_sigma` must be >= 0"),
    ("inverse", 'fit_offsets = "per_row"', r"fit_offsets.*choose one of"),
])
def test_recording_and_mesh_keys_are_checked(tmp_path, section, text, match):
    (tmp_path / "head.msh").write_text("")
    (tmp_path / "rec.json").write_text('{"Freq": [10]}')
    (tmp_path / "volts.csv").write_text("volts\n0.1\n0.2\n")
    text = text.format(head=tmp_path / "head.msh", rec=tmp_path / "rec.json",
                       volts=tmp_path / "volts.csv")
    with pytest.raises(ValueError, match=match):
        load_config(_write(tmp_path, f"[{section}]\n{text}\n"))


def test_fixed_length_lists_convert_their_values(tmp_path):
    # A fixed-length tuple from TOML held the annotation's types instead of the values
    # (zip(args, value) unpacked the wrong way round) until issue 15's fit_priors needed one.
    cfg = load_config(_write(tmp_path, "[inverse]\ncentre_mm = [0, 20, 30.5]\n"
                                       "fit_init_s_m = [0.3, 1.79, 0.02, 0.44]\n"))
    assert cfg.inverse.centre_mm == (0.0, 20.0, 30.5)
    assert cfg.inverse.fit_init_s_m == (0.3, 1.79, 0.02, 0.44)
