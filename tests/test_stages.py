"""The forward and inverse pipeline stages on a ready-made mesh (a 4-shell sphere)."""

import dataclasses
import json

import numpy as np
import pytest

from jaxhead import save_mesh
from jaxhead.run.config import (ElectrodeConfig, ForwardConfig, InputConfig, InverseConfig,
                            RunConfig)
from jaxhead.run import StageError
from jaxhead.run.pipeline import run_pipeline
from jaxhead.protocol import ProtocolConfig
from sphere_mesh import structured_sphere_mesh


def test_forward_and_inverse_stages(tmp_path):
    mesh = structured_sphere_mesh(h_mm=20.0)
    (tmp_path / "run/mri/mesh").mkdir(parents=True)
    save_mesh(mesh, tmp_path / "run/mri/mesh/mesh.vtu")
    cfg = RunConfig(
        out_dir=str(tmp_path / "run"), stages=("forward", "inverse"),
        input=InputConfig(modalities=("mri",)),
        electrodes=ElectrodeConfig(layout=16, radius_mm=8.0),
        protocol=ProtocolConfig(kind="opposite"),
        forward=ForwardConfig(sigma_s_m={"skull": 0.02}),
        inverse=InverseConfig(centre_mm=(0.0, 20.0, 30.0), radius_mm=20.0, cell_mm=15.0,
                              fit=True),
    )
    res = run_pipeline(cfg, progress=lambda s: None)
    out = tmp_path / "run/mri"
    rows = np.loadtxt(out / "forward/voltages.csv", delimiter=",", skiprows=2)  # comment, header
    assert rows.shape == (res["mri"]["forward"]["n_rows"], 5)
    # The forward stage used the configured skull conductivity, the defaults elsewhere.
    from jaxhead.electrodes import place_electrodes, spread_positions
    from jaxhead.fem import build_forward_model, simulate
    from jaxhead.protocol import opposite

    el = place_electrodes(mesh, spread_positions(mesh, 16), radius_mm=8.0)
    v = simulate(build_forward_model(mesh, el), np.array([0.3, 1.79, 0.02, 0.44]), opposite(16))
    np.testing.assert_allclose(rows[:, 4], np.asarray(v), rtol=1e-6)
    assert (out / "forward/scalp_potential.png").stat().st_size > 10_000
    inv = json.loads((out / "inverse/done.json").read_text())["summary"]
    # Reconstruction quality is tested in test_inverse_recovery.py; here: the stage ran and
    # measured a blob inside the head (radius 96 mm).
    assert 0 <= inv["localisation_error_mm"] < 96 and inv["n_cells"] > 10, inv
    assert (out / "inverse/reconstruction.png").exists()
    # The fit ran to convergence (its accuracy: tests/test_fit.py) and reported its cost.
    assert (out / "inverse/fit.txt").exists() and inv["fit_n_forward"] >= 2, inv
    assert np.all(np.isfinite(inv["fit_rel_error"])) and set(inv["seconds"]) >= {
        "jacobian_grid", "reconstruct", "fit"}, inv


def test_inverse_stage_fits_measured_voltages(tmp_path):
    # Voltages written by the forward stage (skull 0.02 S/m) come back as "measured" data: the
    # fit recovers the conductivities that made them, and a changed file reruns the stage.
    mesh = structured_sphere_mesh(h_mm=20.0)
    (tmp_path / "run/mri/mesh").mkdir(parents=True)
    save_mesh(mesh, tmp_path / "run/mri/mesh/mesh.vtu")
    common = dict(out_dir=str(tmp_path / "run"), input=InputConfig(modalities=("mri",)),
                  electrodes=ElectrodeConfig(layout=16, radius_mm=8.0),
                  protocol=ProtocolConfig(kind="opposite"),
                  forward=ForwardConfig(sigma_s_m={"skull": 0.02}))
    run_pipeline(RunConfig(stages=("forward",), **common), progress=lambda s: None)
    measured = tmp_path / "measured.csv"
    measured.write_text((tmp_path / "run/mri/forward/voltages.csv").read_text())
    cfg = RunConfig(stages=("forward", "inverse"), **common,
                    inverse=InverseConfig(cell_mm=15.0, measured_path=str(measured)))
    inv = run_pipeline(cfg, progress=lambda s: None)["mri"]["inverse"]
    np.testing.assert_allclose(inv["fit_sigma"], [0.3, 1.79, 0.02, 0.44], rtol=1e-3)
    assert "fit_rel_error" not in inv  # no truth for measured data
    assert str(measured) in (tmp_path / "run/mri/inverse/fit.txt").read_text()
    # Same file: up to date. Edited file (other voltages): the inverse stage runs again.
    lines = []
    assert run_pipeline(cfg, progress=lines.append)
    assert any("inverse: up to date" in s for s in lines), lines
    from jaxhead.protocol import load_voltages, opposite, save_voltages

    p = opposite(16)
    save_voltages(measured, p, 1.05 * load_voltages(measured, p))
    lines = []
    inv2 = run_pipeline(cfg, progress=lines.append)["mri"]["inverse"]
    assert any("inverse: running" in s for s in lines) and inv2["fit_sigma"] != inv["fit_sigma"]
    # Issue 14: a one-column file in reversed order was fitted (NaN standard errors, exit 0).
    volts = load_voltages(measured, p)
    one_col = tmp_path / "one_column.csv"
    one_col.write_text("volts\n" + "".join(f"{v!r}\n" for v in volts[::-1]))
    bad = dataclasses.replace(cfg, inverse=InverseConfig(cell_mm=15.0, measured_path=str(one_col)))
    with pytest.raises(StageError, match="one_column.csv.*protocol"):
        run_pipeline(bad, progress=lambda s: None, report=False)
    # Issue 14: a zero voltage ended a fit after a minute naming neither file nor line.
    zero = volts.copy()
    zero[3] = 0.0
    save_voltages(measured, p, zero)
    with pytest.raises(StageError, match=r"measured.csv.*protocol row 3 .*is 0.0 V.*noise_floor"):
        run_pipeline(cfg, progress=lambda s: None, report=False)
    with pytest.raises(ValueError, match="measured_path"):
        InverseConfig(measured_path=str(tmp_path / "missing.csv"))
    with pytest.raises(ValueError, match="noise_floor"):
        InverseConfig(noise_floor=-0.1)
    with pytest.raises(ValueError, match="approx_error_draws"):
        InverseConfig(approx_error_draws=1)


def test_inverse_stage_fit_with_the_approximation_error(tmp_path):
    # Measured voltages from a finer mesh (9 mm grid) at skull 0.02 S/m, fitted on the run's
    # 18 mm mesh: the approximation-error model against the finer mesh, configured by path,
    # takes the fit from a biased one to the truth (tests/test_approx_error.py has the algebra).
    from jaxhead.electrodes import place_electrodes, spread_positions
    from jaxhead.fem import build_forward_model, simulate
    from jaxhead.protocol import opposite, save_voltages

    coarse, fine = structured_sphere_mesh(h_mm=18.0), structured_sphere_mesh(h_mm=9.0)
    (tmp_path / "run/mri/mesh").mkdir(parents=True)
    save_mesh(coarse, tmp_path / "run/mri/mesh/mesh.vtu")
    save_mesh(fine, tmp_path / "fine.vtu")
    truth = np.array([0.3, 1.79, 0.02, 0.44])
    el = place_electrodes(fine, spread_positions(coarse, 16), radius_mm=10.0)
    p = opposite(16)
    save_voltages(tmp_path / "measured.csv", p,
                  np.asarray(simulate(build_forward_model(fine, el), truth, p)))
    def cfg(ae_mesh):
        return RunConfig(
            out_dir=str(tmp_path / "run"), stages=("inverse",),
            input=InputConfig(modalities=("mri",)),
            electrodes=ElectrodeConfig(layout=16, radius_mm=10.0),
            protocol=ProtocolConfig(kind="opposite"),
            inverse=InverseConfig(cell_mm=15.0, measured_path=str(tmp_path / "measured.csv"),
                                  approx_error_mesh=ae_mesh))

    # Without the error model the fit runs away (brain 200 S/m, NaN standard errors): an error
    # naming the file, not a result (it was written as one, exit 0, before issue 14).
    with pytest.raises(StageError, match="measured.csv.*no finite standard errors"):
        run_pipeline(cfg(None), progress=lambda s: None, report=False)
    corrected = run_pipeline(cfg(str(tmp_path / "fine.vtu")), progress=lambda s: None,
                             report=False)["mri"]["inverse"]
    err = np.abs(np.asarray(corrected["fit_sigma"]) / truth - 1)
    print("with the error model", err)
    assert corrected["approx_error_rel"] > 0.01 and "approx_error" in corrected["seconds"]
    assert np.all(err < 0.03), err  # measured: 0.3 / 0.8 / 0.04 / 0.03 %
    assert "approximation-error model" in (tmp_path / "run/mri/inverse/fit.txt").read_text()
