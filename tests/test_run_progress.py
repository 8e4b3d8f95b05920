"""Progress of long stages: a live line on a terminal, plain lines elsewhere, quiet under CI."""

import io
import time

from jaxhead.run import stage
from jaxhead.run.config import InputConfig, RunConfig
from jaxhead.run.pipeline import run_pipeline
from jaxhead.run.progress import heartbeat, progress_mode


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_modes(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    assert progress_mode(_Tty()) == "live" and progress_mode(io.StringIO()) == "lines"
    monkeypatch.setenv("CI", "true")
    assert progress_mode(_Tty()) == "quiet"


def test_plain_lines_while_a_stage_runs(tmp_path, monkeypatch):
    monkeypatch.delenv("CI", raising=False)

    @stage(config=("input",))
    def slow(cfg, subject):
        time.sleep(0.5)
        (subject.dir("input") / "x.txt").write_text("x")
        return {}

    lines = []
    cfg = RunConfig(out_dir=str(tmp_path / "run"), input=InputConfig(modalities=("mri",)))
    run_pipeline(cfg, stages={"input": slow}, progress=lines.append, heartbeat_s=0.1,
                 report=False)
    beats = [s for s in lines if "[mri] input: still running (0:00)" in s]
    assert 2 <= len(beats) <= 6, lines
    # Under CI nothing but the start and end lines.
    monkeypatch.setenv("CI", "true")
    lines.clear()
    run_pipeline(cfg, stages={"input": slow}, progress=lines.append, heartbeat_s=0.1,
                 force=True, report=False)
    assert not any("still running" in s for s in lines) and len(lines) == 2, lines


def test_live_line_on_a_terminal():
    tty = _Tty()
    with heartbeat("[mri] mesh", print, mode="live", stream=tty):
        time.sleep(1.3)
    out = tty.getvalue()
    assert "\r[mri] mesh: still running (0:01)" in out and out.endswith("\r\033[K")
