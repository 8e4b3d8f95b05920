"""Issue 5 on a phantom head (slow): conductivity fit and perturbation localisation.

Two independent fTetWild meshes of the same 2 mm MRI phantom (jaxhead.phantom.make_head): the
data mesh with the demo's sizes (configs/demo.toml: ~590k tets) and a coarser reconstruction /
fit mesh (brain 12 mm, CSF 4, skull 4.5, scalp 6 mm). The data mesh's surfaces are remeshed
with other edge lengths, so the two differ in geometry as well as resolution: no inverse crime
(Kaipio & Somersalo 2005, sec. 1.2). 32 electrodes (6 mm discs) at the same positions on both;
drives (i, i + k), k = 1, 4, 8, 16, each measured on every adjacent pair that avoids it; 0.5 %
Gaussian noise per channel relative to the standing voltage.

Meshing takes 5-20 minutes per mesh on a shared 2-core machine. Set JAXHEAD_HEAD_MESHES to a
folder to cache them there (data.vtu, recon.vtu; reused when present).
"""

import os
from pathlib import Path

import numpy as np
import pytest

from jaxhead.inverse.approx_error import approximation_error, sample_conductivities
from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import build_forward_model
from jaxhead.fem import simulate
from jaxhead.inverse.fit import LineSearchGaussNewton, fit_conductivities
from jaxhead.inverse import (TSVD, Tikhonov, add_noise, image_metrics, jacobian_grid, make_grid,
                             noise_std, reconstruct, simulate_difference, spherical_perturbation,
                             svd)
from jaxhead.protocol import Protocol, pair_drive
from jaxhead.tissue import default_sigma

pytestmark = pytest.mark.slow

N_ELEC = 32
SIGMA = default_sigma()
TRUE = SIGMA * np.array([1.1, 0.9, 1.2, 0.95])  # brain, CSF, skull, scalp (S/m)
# Surface and tet sizes (mm) of the data mesh (configs/demo.toml) and the reconstruction mesh.
DATA_SURF = {"brain": 5.0, "csf": 3.0, "skull": 3.5, "scalp": 4.5}
DATA_TET = {"brain": 8.0, "csf": 3.0, "skull": 3.5, "scalp": 4.5}
RECON_SURF = {"brain": 7.0, "csf": 4.0, "skull": 4.5, "scalp": 6.0}
RECON_TET = {"brain": 12.0, "csf": 4.0, "skull": 4.5, "scalp": 6.0}


def _mesh(path: Path | None, surf_mm, tet_mm, max_opt):
    from jaxhead.io import load_mesh, save_mesh
    from jaxhead.geometry import MeshConfig, tetrahedralize
    from jaxhead.phantom import make_head
    from jaxhead.geometry.layers import make_layers
    from jaxhead.geometry.surface import SurfaceConfig, extract_surfaces

    if path is not None and path.exists():
        return load_mesh(path)
    _, labels = make_head("mri", voxel_mm=2.0, seed=0)
    surfs = extract_surfaces(make_layers(labels), SurfaceConfig(edge_mm=surf_mm))
    mesh = tetrahedralize(surfs, MeshConfig(edge_mm=tet_mm, stop_energy=30.0,
                                            max_opt_iterations=max_opt))
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_mesh(mesh, path)
    return mesh


@pytest.fixture(scope="module")
def head():
    cache = os.environ.get("JAXHEAD_HEAD_MESHES")
    folder = Path(cache) if cache else None
    data = _mesh(folder / "data.vtu" if folder else None, DATA_SURF, DATA_TET, 20)
    recon = _mesh(folder / "recon.vtu" if folder else None, RECON_SURF, RECON_TET, 10)
    pos = spread_positions(recon, N_ELEC)
    data_model = build_forward_model(data, place_electrodes(data, pos, radius_mm=6.0))
    model = build_forward_model(recon, place_electrodes(recon, pos, radius_mm=6.0))
    protocol = Protocol(np.concatenate([pair_drive(N_ELEC, i, (i + k) % N_ELEC).rows
                                        for k in (1, 4, 8, 16) for i in range(N_ELEC)]))
    ext = data.nodes.max(0) - data.nodes.min(0)
    # Head diameter: the smaller horizontal extent (left-right), the stricter 10 % bar.
    return dict(data=data, recon=recon, data_model=data_model, model=model,
                protocol=protocol, diameter_mm=float(min(ext[0], ext[1])))


def test_meshes_differ(head):
    # Not an inverse crime: different node sets and a measurable voltage mismatch.
    assert head["data"].n_tets > 2 * head["recon"].n_tets
    v_data = np.asarray(simulate(head["data_model"], TRUE, head["protocol"]))
    v_recon = np.asarray(simulate(head["model"], TRUE, head["protocol"]))
    mismatch = np.linalg.norm(v_data - v_recon) / np.linalg.norm(v_data)
    print(f"voltage mismatch between the meshes: {mismatch:.4f}")
    assert mismatch > 1e-3, mismatch


def _fit(model, data_model, protocol, seed=0):
    v = np.asarray(simulate(data_model, TRUE, protocol))
    measured = add_noise(v, 0.5, seed=seed)
    res = fit_conductivities(model, protocol, measured, init=SIGMA, noise_std=noise_std(v, 0.5),
                             solver=LineSearchGaussNewton(rtol=1e-6, atol=1e-6), throw=False)
    err = np.abs(res.sigma / TRUE - 1)
    print(res.table(), "\nrelative errors (brain, csf, skull, scalp):", err)
    return res, err


def test_fit_recovers_head_conductivities_same_mesh(head):
    # Data from the fitted mesh itself (an inverse crime): the noise-limited accuracy.
    res, err = _fit(head["data_model"], head["data_model"], head["protocol"])
    # Issue 5's bar: brain, CSF, scalp within 2 %, skull within 10 %.
    assert res.success
    assert np.all(err[[0, 1, 3]] < 0.02) and err[2] < 0.10, err


def test_fit_recovers_head_conductivities_from_other_mesh(head):
    # Data from the finer mesh, fitted on the coarser one. The plain fit absorbs the 4 % voltage
    # mismatch into the conductivities (measured with Levenberg-Marquardt: brain +164 %,
    # CSF -76 %, not converged); the approximation-error model of the fit mesh against the finer
    # one, from 20 prior draws (not the true conductivities), removes that bias. Here the finer
    # mesh both makes the data and stands for the head in the error model, as in the
    # approximation-error literature's simulations; experiments/cross_mesh_fit.py also estimates
    # it on a third mesh that did not make the data.
    ae = approximation_error(head["data_model"], head["model"], sample_conductivities(20, seed=7),
                             head["protocol"])
    v = np.asarray(simulate(head["data_model"], TRUE, head["protocol"]))
    for seed in (0, 1):
        res = fit_conductivities(head["model"], head["protocol"], add_noise(v, 0.5, seed=seed),
                                 init=SIGMA, noise_std=noise_std(v, 0.5), approx_error=ae,
                                 solver=LineSearchGaussNewton(rtol=1e-6, atol=1e-6))
        err = np.abs(res.sigma / TRUE - 1)
        print(res.table(TRUE), "\nrelative errors (brain, csf, skull, scalp):", err)
        assert res.success
        assert np.all(err[[0, 1, 3]] < 0.02) and err[2] < 0.10, err


@pytest.mark.xfail(strict=True, reason=(
    "known gap (issue 5 report): at 0.5 % noise per channel relative to the standing voltage, "
    "||dv|| / ||noise|| is 0.02-0.04 for a 1.5 cm, +20 % ball (0.04-0.09 at 2 cm); GCV keeps "
    "1-5 components and the blob lands 18-47 mm off (bar 16 mm), and no fixed truncation does "
    "better. Noise-free, 64-128 components put 4 of 5 places within 2-7 mm; at 0.05 % noise GCV "
    "still lands 3-41 mm off (experiments/head_localisation.py)"))
@pytest.mark.parametrize("offset_mm", [(0.0, 0.0, 0.0), (-35.0, 0.0, 15.0), (0.0, -40.0, 15.0)],
                         ids=["central", "left", "posterior"])
def test_localises_a_brain_perturbation(head, offset_mm):
    data, recon = head["data"], head["recon"]
    grid = make_grid(recon, 10.0, tissues=["brain"])
    Jg, _ = jacobian_grid(head["model"], SIGMA, head["protocol"], grid, return_volts=True)
    s_data = SIGMA[data.labels - 1]
    v0 = np.asarray(simulate(head["data_model"], SIGMA, head["protocol"]))
    std = noise_std(v0, 0.5, floor=0.03)  # as tests/test_inverse_recovery.py
    # Half-NOSER (exponent 0.5, EIDORS prior_noser's default): full NOSER (1.0, as on the
    # sphere) lifts the brain cells farthest from the electrodes into spurious peaks on a head.
    dec = svd(Jg / std[:, None], normalise=0.5)
    b = data.labels == 1
    cen, vol = data.centroids()[b], data.tet_volumes()[b]
    centre = (cen * vol[:, None]).sum(0) / vol.sum() + np.asarray(offset_mm)
    radius = 15.0  # a 3 cm ball (1.5 cm radius), +20 %
    pert = spherical_perturbation(data, s_data, centre, radius, 0.2, tissue="brain")
    dv, _ = simulate_difference(head["data_model"], s_data, pert, head["protocol"],
                                noise_percent=0.5, seed=1)
    for method in (TSVD(noise_weighted=True, normalise=0.5),
                   Tikhonov(noise_weighted=True, normalise=0.5)):
        rec = reconstruct(None, dv, method, noise_std=std, decomposition=dec)
        m = image_metrics(np.asarray(rec.image), grid.centres, grid.volumes, centre, radius,
                          sign=1)
        print(f"{offset_mm} {rec.method}: k={rec.k:.1f}, error {m.localisation_error_mm:.1f} mm "
              f"(bar {0.1 * head['diameter_mm']:.1f}), diameter {m.diameter_mm:.1f} mm")
        assert m.localisation_error_mm < 0.1 * head["diameter_mm"], (rec.method, m)
