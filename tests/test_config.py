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
