"""kill -9 of a running `jaxhead study` (driver and worker processes), then a rerun: only the
missing samples run; the finished ones are neither recomputed nor rewritten (issue 13)."""

import csv
import json
import os
import signal
import subprocess
import sys
import time

import pytest
from sphere_mesh import structured_sphere_mesh
from test_study_engine import TOML as ENGINE_TOML

from jaxhead.io import save_mesh
from jaxhead.study import run_study

# the engine test's study (sphere head, 8 electrodes) without imaging: its two csf grf samples
# and six electrode samples
_HEAD, _GRF_CSF = ENGINE_TOML.split("[[study.perturbations]]")[:2]
TOML = _HEAD + """imaging = false

[[study.perturbations]]""" + _GRF_CSF + """[[study.perturbations]]
kind = "electrode_position"
amplitude = 2.0
samples = 6
"""


@pytest.mark.slow  # ~70 s: two cold starts (test_study_engine's rerun test is the fast check)
def test_kill_9_mid_study_then_rerun_runs_only_the_missing_samples(tmp_path):
    mesh = structured_sphere_mesh(h_mm=16.0)
    save_mesh(mesh, tmp_path / "sphere.vtu")
    cfg = tmp_path / "study.toml"
    cfg.write_text(TOML.format(out=tmp_path / "run", mesh=tmp_path / "sphere.vtu"))
    samples = tmp_path / "run" / "study" / "samples"
    # its own session: SIGKILL to the process group takes the Dask nanny and worker too
    p = subprocess.Popen([sys.executable, "-m", "jaxhead", "study", str(cfg), "--workers", "1",
                          "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True, start_new_session=True,
                         env={**os.environ, "PYTHONPATH": os.getcwd()})
    t0 = time.monotonic()
    while not (samples.is_dir() and list(samples.glob("0*.json"))):
        assert p.poll() is None, p.stderr.read()
        assert time.monotonic() - t0 < 240, "no sample finished within 240 s"
        time.sleep(0.02)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    before = {f.name: (f.stat().st_mtime_ns, f.read_bytes()) for f in samples.glob("0*.json")}
    assert 1 <= len(before) < 8, sorted(before)
    assert not (tmp_path / "run" / "study" / "samples.csv").exists()

    out = run_study(cfg, workers=1, progress=False)
    s = json.loads((out / "summary.json").read_text())
    assert s["run"]["skipped_finished"] == len(before)
    assert s["run"]["ran"] == 8 - len(before)
    for name, (mtime, data) in before.items():  # not recomputed, not rewritten
        f = samples / name
        assert f.stat().st_mtime_ns == mtime and f.read_bytes() == data, name
    with open(out / "samples.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8 and all(not r["error"] for r in rows), [r["error"] for r in rows]
    assert len(list(samples.glob("0*.json"))) == 8
