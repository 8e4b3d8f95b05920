"""Difference imaging of a brain perturbation in a four-shell sphere, without the inverse crime.

Data come from a finer mesh (10 mm grid, 64k tets) than the reconstruction mesh (14 mm, 35k
tets), with the same 32 electrodes (same centres and radius), 0.5 % Gaussian noise per channel
relative to the standing voltage (the seed paper's model), and a 2 cm radius, +20 % ball in the
brain. Reconstruction: the coarse mesh's Jacobian summed into 10 mm brain cells, whitened by the
noise level and column-normalised (NOSER scaling), then TSVD and Tikhonov with GCV. The bar
(issue 5): localisation error below 10 % of the head diameter (19.2 mm).

Why whitened and normalised: with noise proportional to each channel's standing voltage, the
noise norm is ~8x the signal norm here, and plain (unweighted) TSVD/GCV keeps 1-7 singular
values and misplaces the blob by 20-70 mm; unnormalised images are pulled towards the most
sensitive, superficial cells. Weights trust channels with near-zero standing voltage only down
to 3 % of the RMS standing voltage (`noise_std(..., floor=0.03)`): beyond that the coarse
mesh's modelling error, not the noise, dominates those channels. Over 5 noise seeds and 5
positions this recipe localised within 4-24 mm (median ~9 mm); the two positions tested here
stayed within 2-12 mm for both methods (see the report of issue 5).
"""

import numpy as np
import pytest

from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import build_forward_model, jacobian, simulate
from jaxhead.inverse import (TSVD, Tikhonov, image_metrics, jacobian_grid, jacobian_to_grid,
                             make_grid, noise_std, reconstruct, simulate_difference,
                             spherical_perturbation, svd)
from jaxhead.protocol import Protocol, adjacent, opposite
from jaxhead.tissue import default_sigma
from sphere_mesh import RADII_MM, structured_sphere_mesh

SIGMA = default_sigma()
N_ELEC = 32
RADIUS_MM = 20.0
HEAD_DIAMETER_MM = 2 * RADII_MM[-1]


@pytest.fixture(scope="module")
def setup():
    fine = structured_sphere_mesh(h_mm=10.0)
    coarse = structured_sphere_mesh(h_mm=14.0)
    # Electrodes over the whole sphere (a ball has no neck), same positions and radius on both.
    pos = spread_positions(coarse, N_ELEC, max_polar_deg=180.0)
    fine_model = build_forward_model(fine, place_electrodes(fine, pos, radius_mm=10.0))
    model = build_forward_model(coarse, place_electrodes(coarse, pos, radius_mm=10.0))
    protocol = Protocol(np.concatenate([opposite(N_ELEC).rows, adjacent(N_ELEC).rows]))
    J, v_coarse = jacobian(model, SIGMA, protocol, return_volts=True)
    grid = make_grid(coarse, 10.0, tissues=["brain"])
    Jg = jacobian_to_grid(J, grid)
    v_fine = np.asarray(simulate(fine_model, SIGMA, protocol))
    std = noise_std(v_fine, 0.5, floor=0.03)
    dec = svd(Jg / std[:, None], normalise=True)  # one SVD serves both methods
    return dict(fine=fine, coarse=coarse, fine_model=fine_model, model=model, J=J,
                protocol=protocol, grid=grid, Jg=Jg, std=std, dec=dec,
                v_fine=v_fine, v_coarse=np.asarray(v_coarse))


def test_data_mesh_differs_from_reconstruction_mesh(setup):
    # Not an inverse crime: the two meshes' standing voltages differ by several percent
    # (the coarse mesh resolves the 4 mm CSF and 6 mm skull with one or two layers).
    mismatch = np.linalg.norm(setup["v_fine"] - setup["v_coarse"]) / np.linalg.norm(setup["v_fine"])
    assert 0.01 < mismatch < 0.2, mismatch


def test_difference_data_match_the_jacobian_to_first_order(setup):
    # Taylor: V(s + e d) - V(s) = e J d + O(e^2), so the remainder falls 10x per 10x in e.
    coarse, model, protocol = setup["coarse"], setup["model"], setup["protocol"]
    s_tet = SIGMA[coarse.labels - 1]
    ball = spherical_perturbation(coarse, s_tet, [30.0, 0.0, 10.0], RADIUS_MM, 1.0,
                                  tissue="brain") - s_tet
    rem = []
    for eps in (1e-2, 1e-3):
        dv, _ = simulate_difference(model, s_tet, s_tet + eps * ball, protocol)
        lin = np.asarray(setup["J"]) @ (eps * ball)
        rem.append(np.linalg.norm(dv - lin) / np.linalg.norm(lin))
    assert rem[0] < 0.02 and 5 < rem[0] / rem[1] < 20, rem  # second order: ratio ~10


@pytest.mark.parametrize("centre", [(0.0, 0.0, 0.0), (40.0, 0.0, 20.0)],
                         ids=["central", "off-centre"])
def test_localises_a_2cm_brain_perturbation(setup, centre):
    fine, grid = setup["fine"], setup["grid"]
    s_fine = SIGMA[fine.labels - 1]
    pert = spherical_perturbation(fine, s_fine, centre, RADIUS_MM, 0.2, tissue="brain")
    dv, _ = simulate_difference(setup["fine_model"], s_fine, pert, setup["protocol"],
                                noise_percent=0.5, seed=1)
    for method in (TSVD(noise_weighted=True, normalise=True),
                   Tikhonov(noise_weighted=True, normalise=True)):
        rec = reconstruct(None, dv, method, noise_std=setup["std"], decomposition=setup["dec"])
        m = image_metrics(np.asarray(rec.image), grid.centres, grid.volumes, centre, RADIUS_MM)
        print(f"{centre} {rec.method}: k={rec.k:.1f} error {m.localisation_error_mm:.1f} mm, "
              f"diameter {m.diameter_mm:.1f} mm, volume ratio {m.volume_ratio:.2f}")
        assert m.peak_value > 0, "the image's dominant sign is wrong"
        assert m.localisation_error_mm < 0.1 * HEAD_DIAMETER_MM, (rec.method, m)


def test_jacobian_grid_equals_summed_tet_jacobian(setup):
    # Independent route: the dense per-tet reciprocity Jacobian, columns summed by np.add.at.
    # Both sum the same float64 products in a different order: agreement to ~1e-12 relative.
    # A tile width that does not divide the grid's tet count exercises the padded last tile.
    Jg, v = jacobian_grid(setup["model"], SIGMA, setup["protocol"], setup["grid"],
                          tile_tets=1000, return_volts=True)
    np.testing.assert_allclose(Jg, setup["Jg"], rtol=1e-9, atol=1e-12 * np.abs(setup["Jg"]).max())
    np.testing.assert_allclose(v, setup["v_coarse"], rtol=1e-12)
    with pytest.raises(ValueError, match="grid"):
        jacobian_grid(setup["fine_model"], SIGMA, setup["protocol"], setup["grid"])
