"""The README's API tour runs as written (slow: it meshes a whole 2 mm head with fTetWild)."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_a_python_tour():
    blocks = _python_blocks()
    assert blocks, "README.md lost its ```python API tour"
    for block in blocks:
        compile(block, "README.md", "exec")  # at least valid Python


@pytest.mark.slow
def test_readme_tour_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # pytetwild writes a scratch file into the working directory
    for block in _python_blocks():
        namespace: dict = {}
        exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102
