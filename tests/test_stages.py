"""The forward and inverse pipeline stages on a ready-made mesh (a 4-shell sphere)."""

import json

import numpy as np

from jaxhead import save_mesh
from jaxhead.config import (ElectrodeConfig, ForwardConfig, InputConfig, InverseConfig,
                            RunConfig)
from jaxhead.pipeline import run_pipeline
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
    rows = np.loadtxt(out / "forward/voltages.csv", delimiter=",", skiprows=1)
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
