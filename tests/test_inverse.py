"""TSVD/Tikhonov against naive dense solutions, parameter rules, grids and image metrics."""

import warnings

import numpy as np
import pytest
from scipy.spatial import Delaunay

from jaxhead import TetMesh, orient_tets
from jaxhead.inverse import (
    Grid,
    TSVD,
    Tikhonov,
    add_noise,
    grid_to_tets,
    image_metrics,
    jacobian_to_grid,
    make_grid,
    noise_std,
    reconstruct,
    reconstruct_batch,
    spherical_perturbation,
    svd,
)


def blur_problem(m=60, n=80, width=0.08, seed=0):
    """A discrete ill-posed problem: Gaussian blur of a smooth profile (like Hansen's 'shaw')."""
    s = np.linspace(0, 1, m)[:, None]
    t = np.linspace(0, 1, n)[None, :]
    J = np.exp(-((s - t) ** 2) / (2 * width**2)) / n
    x_true = np.exp(-((t[0] - 0.4) ** 2) / 0.01) + 0.5 * np.exp(-((t[0] - 0.7) ** 2) / 0.003)
    b = J @ x_true
    return J, x_true, b


@pytest.mark.parametrize("shape", [(20, 200), (200, 20), (60, 50)])
def test_svd_paths_agree(shape):
    rng = np.random.default_rng(1)
    J = rng.standard_normal(shape) @ np.diag(np.geomspace(1, 1e-3, shape[1]))
    s_ref = np.linalg.svd(J, compute_uv=False)
    for gram in (True, False):
        d = svd(J, gram=gram)
        # Singular values >= 1e-3 s_max: the Gram route's relative error is ~eps (s_max/s)^2
        # <= 1e-10 (Golub & Van Loan 2013, sec. 8.6), so 1e-9 holds for both routes.
        np.testing.assert_allclose(np.asarray(d.s), s_ref[: d.s.shape[0]], rtol=1e-9)
        np.testing.assert_allclose(np.asarray(d.u * d.s) @ np.asarray(d.vt), J, atol=1e-12)
        np.testing.assert_allclose(np.asarray(d.u.T @ d.u), np.eye(d.s.shape[0]), atol=1e-9)


@pytest.mark.parametrize("shape", [(40, 30), (30, 400)])
def test_tsvd_matches_truncated_pseudo_inverse(shape):
    rng = np.random.default_rng(0)
    J = rng.standard_normal(shape)
    b = rng.standard_normal(shape[0])
    k = 7
    u, s, vt = np.linalg.svd(J, full_matrices=False)
    x_ref = vt[:k].T @ ((u[:, :k].T @ b) / s[:k])
    rec = reconstruct(J, b, TSVD(k))
    np.testing.assert_allclose(np.asarray(rec.image), x_ref, rtol=1e-8, atol=1e-12)
    assert rec.k == k and rec.rule == "given"
    np.testing.assert_allclose(rec.residual_norm, np.linalg.norm(J @ x_ref - b), rtol=1e-8)


@pytest.mark.parametrize("shape", [(40, 30), (30, 400)])
def test_tikhonov_matches_normal_equations(shape):
    rng = np.random.default_rng(2)
    J = rng.standard_normal(shape)
    b = rng.standard_normal(shape[0])
    lam = 0.7
    x_ref = np.linalg.solve(J.T @ J + lam**2 * np.eye(shape[1]), J.T @ b)
    rec = reconstruct(J, b, Tikhonov(lam))
    np.testing.assert_allclose(np.asarray(rec.image), x_ref, rtol=1e-8, atol=1e-12)


def test_noise_weighted_tikhonov():
    rng = np.random.default_rng(3)
    J = rng.standard_normal((25, 15))
    b = rng.standard_normal(25)
    std = rng.uniform(0.5, 2.0, 25)
    W = np.diag(1 / std)
    lam = 0.3
    x_ref = np.linalg.solve(J.T @ W @ W @ J + lam**2 * np.eye(15), J.T @ W @ W @ b)
    rec = reconstruct(J, b, Tikhonov(lam, noise_weighted=True), noise_std=std)
    np.testing.assert_allclose(np.asarray(rec.image), x_ref, rtol=1e-8)


def test_gcv_choice_is_near_optimal():
    J, x_true, b = blur_problem()
    rng = np.random.default_rng(4)
    sigma = 1e-3 * np.abs(b).max()
    bn = b + sigma * rng.standard_normal(b.shape)
    dec = svd(J)
    errs = [np.linalg.norm(np.asarray(reconstruct(J, bn, TSVD(k), decomposition=dec).image) - x_true)
            for k in range(1, 40)]
    best = min(errs)
    for method in (TSVD(), Tikhonov()):
        rec = reconstruct(J, bn, method)
        err = np.linalg.norm(np.asarray(rec.image) - x_true)
        # GCV is not the oracle; within a factor 3 of the best TSVD error (Hansen 1998, ch. 7).
        assert err < 3 * best, (method, err, best)
        assert rec.rule == "gcv"


def test_discrepancy_rule_meets_the_noise_level():
    J, x_true, b = blur_problem()
    rng = np.random.default_rng(5)
    sigma = 1e-3 * np.abs(b).max()
    bn = b + sigma * rng.standard_normal(b.shape)
    target = 1.05 * np.sqrt(b.size) * sigma
    rec = reconstruct(J, bn, TSVD(rule="discrepancy"), noise_std=sigma)
    assert rec.residual_norm <= target
    prev = reconstruct(J, bn, TSVD(int(rec.k) - 1))
    assert prev.residual_norm > target  # the smallest k that meets it
    rec = reconstruct(J, bn, Tikhonov(rule="discrepancy"), noise_std=sigma)
    assert rec.residual_norm <= target * 1.0001
    assert rec.residual_norm > 0.5 * target  # not over-fitted to the noise


def test_reconstruct_errors():
    J = np.ones((4, 3))
    with pytest.raises(ValueError, match="one voltage change per protocol row"):
        reconstruct(J, np.ones(5))
    with pytest.raises(ValueError, match="needs `noise_std`"):
        reconstruct(J, np.ones(4), TSVD(rule="discrepancy"))
    with pytest.raises(ValueError, match="NaN"):
        reconstruct(J, np.array([1, np.nan, 0, 0]))
    with pytest.raises(ValueError, match=">= 1"):
        TSVD(0)
    with pytest.raises(ValueError, match="> 0"):
        Tikhonov(-1.0)


def small_mesh(seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-20, 20, (400, 3))
    tets = Delaunay(pts).simplices
    tets, _ = orient_tets(pts, tets)
    vol = np.abs(np.einsum("ij,ij->i", np.cross(pts[tets[:, 1]] - pts[tets[:, 0]],
                                                  pts[tets[:, 2]] - pts[tets[:, 0]]),
                           pts[tets[:, 3]] - pts[tets[:, 0]]))
    tets = tets[vol > 1e-9]
    r = np.linalg.norm(pts[tets].mean(1), axis=1)
    labels = np.digitize(r, [8, 12, 16]) + 1
    return TetMesh(pts, tets, labels)


def test_grid_sums_jacobian_columns():
    mesh = small_mesh()
    grid = make_grid(mesh, 10.0)
    np.testing.assert_allclose(grid.volumes.sum(), mesh.tet_volumes().sum(), rtol=1e-12)
    J = np.random.default_rng(0).standard_normal((5, mesh.n_tets))
    P = np.zeros((mesh.n_tets, grid.n_cells))
    P[np.arange(mesh.n_tets), grid.cell_of_tet] = 1
    np.testing.assert_allclose(jacobian_to_grid(J, grid), J @ P, rtol=1e-12)
    # A uniform cell change is the same as changing each of its tets.
    x = np.random.default_rng(1).standard_normal(grid.n_cells)
    np.testing.assert_allclose(J @ grid_to_tets(x, grid), jacobian_to_grid(J, grid) @ x, rtol=1e-10)
    brain = make_grid(mesh, 10.0, tissues=["brain"])
    assert np.all((brain.cell_of_tet >= 0) == (mesh.labels == 1))


def test_grid_merges_partly_filled_cells():
    mesh = small_mesh()
    cell_mm = 6.0
    raw = make_grid(mesh, cell_mm, tissues=["brain"], min_fill=0.0)
    merged = make_grid(mesh, cell_mm, tissues=["brain"], min_fill=0.5)
    full = raw.volumes >= 0.5 * cell_mm**3
    assert 0 < full.sum() < raw.n_cells  # the ball's boundary cuts some cells
    # Full cells stay; every sliver joins one of them; the volume is conserved.
    assert merged.n_cells == full.sum()
    assert np.all(merged.volumes >= 0.5 * cell_mm**3)
    np.testing.assert_allclose(merged.volumes.sum(), raw.volumes.sum(), rtol=1e-12)
    np.testing.assert_array_equal(merged.cell_of_tet >= 0, raw.cell_of_tet >= 0)
    # A tet of a full cell keeps its cell-mates; a sliver tet goes to the nearest full cell.
    cen = mesh.centroids()
    for t in np.flatnonzero(raw.cell_of_tet >= 0):
        mates = raw.cell_of_tet == raw.cell_of_tet[t]
        if full[raw.cell_of_tet[t]]:
            assert np.all(merged.cell_of_tet[mates] == merged.cell_of_tet[t])
        else:
            d = np.linalg.norm(raw.centres[full] - cen[t], axis=1)
            target = merged.cell_of_tet[(raw.cell_of_tet == np.flatnonzero(full)[d.argmin()])][0]
            assert merged.cell_of_tet[t] == target
    with pytest.raises(ValueError, match="min_fill"):
        make_grid(mesh, cell_mm, min_fill=1.5)


def test_perturbation_and_metrics():
    mesh = small_mesh()
    sigma = np.ones(mesh.n_tets)
    pert = spherical_perturbation(mesh, sigma, [0, 0, 0], 10.0, 0.2)
    inside = np.linalg.norm(mesh.centroids(), axis=1) <= 10
    np.testing.assert_allclose(pert[inside], 1.2)
    np.testing.assert_allclose(pert[~inside], 1.0)
    with pytest.raises(ValueError, match="no BRAIN tet"):
        spherical_perturbation(mesh, sigma, [100, 0, 0], 1.0, 0.1, tissue="brain")
    # An exact indicator image of a ball on a fine regular grid: zero error, volume ratio ~1.
    g = np.arange(-30, 30.5, 1.0)
    c = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    img = (np.linalg.norm(c - [5, -3, 2], axis=1) <= 8).astype(float)
    m = image_metrics(img, c, np.ones(len(c)), [5, -3, 2], 8.0)
    assert m == image_metrics(img, Grid(np.full(0, -1), c, np.ones(len(c)), 1.0), [5, -3, 2], 8.0)
    assert m.localisation_error_mm < 1e-9
    assert abs(m.volume_ratio - 1) < 0.03 and abs(m.diameter_mm - 16) < 0.3
    m = image_metrics(-img, c, np.ones(len(c)), [5, -3, 2], 8.0)
    assert m.peak_value == -1


def test_noise_statistics():
    v = np.linspace(1e-3, 2e-3, 50)
    samples = np.stack([add_noise(v, 0.5, seed=s) for s in range(2000)])
    rel_std = samples.std(0) / (0.005 * v)
    assert abs(rel_std.mean() - 1) < 0.03  # 2000 samples: std of the std estimate ~1.6 %
    np.testing.assert_array_equal(add_noise(v, 0.5, seed=3), add_noise(v, 0.5, seed=3))


@pytest.mark.parametrize("method", [TSVD(), Tikhonov(rule="discrepancy"),
                                    Tikhonov(noise_weighted=True)])
def test_batch_equals_loop(method):
    J, x_true, b = blur_problem()
    rng = np.random.default_rng(6)
    # Non-uniform noise: the discrepancy rule then needs per-channel residuals.
    std = 1e-3 * np.abs(b).max() * rng.uniform(0.5, 2.0, b.size)
    B = b + std * rng.standard_normal((5, b.size))
    batch = reconstruct_batch(J, B, method, noise_std=std)
    assert batch.image.shape == (5, J.shape[1]) and batch.k.shape == (5,)
    for i in range(5):
        one = reconstruct(J, B[i], method, noise_std=std)
        np.testing.assert_allclose(np.asarray(batch.image[i]), np.asarray(one.image), rtol=1e-10,
                                   atol=1e-12 * np.abs(np.asarray(one.image)).max())
        assert float(batch.k[i]) == pytest.approx(one.k, rel=1e-12)
        assert float(batch.residual_norm[i]) == pytest.approx(one.residual_norm, rel=1e-9)


def test_discrepancy_with_per_channel_noise():
    # Per-channel residual ||W r|| is computed from the SVD; check it against a dense product.
    J, x_true, b = blur_problem()
    rng = np.random.default_rng(7)
    std = 1e-3 * np.abs(b).max() * rng.uniform(0.3, 3.0, b.size)
    bn = b + std * rng.standard_normal(b.size)
    target = 1.05 * np.sqrt(b.size)
    rec = reconstruct(J, bn, TSVD(rule="discrepancy"), noise_std=std)
    assert np.linalg.norm((J @ np.asarray(rec.image) - bn) / std) <= target
    prev = reconstruct(J, bn, TSVD(int(rec.k) - 1))
    assert np.linalg.norm((J @ np.asarray(prev.image) - bn) / std) > target


def test_reconstruct_batch_errors():
    J = np.ones((4, 3))
    with pytest.raises(ValueError, match="n_batch, n_rows"):
        reconstruct_batch(J, np.ones(4))
    with pytest.raises(ValueError, match="one voltage change per protocol row"):
        reconstruct_batch(J, np.ones((2, 5)))
    with pytest.raises(ValueError, match="reconstruct_batch"):
        reconstruct(J, np.ones((2, 4)))
    with pytest.raises(ValueError, match="TSVD"):
        reconstruct(J, np.ones(4), "tsvd")


def test_normalised_and_weighted_methods_match_dense_formulas():
    rng = np.random.default_rng(8)
    J = rng.standard_normal((25, 40)) * np.geomspace(1, 1e-2, 40)  # columns of unequal norm
    b = rng.standard_normal(25)
    std = rng.uniform(0.5, 2.0, 25)
    W = np.diag(1 / std)
    D = np.diag(np.linalg.norm(W @ J, axis=0))
    lam = 0.4
    # NOSER-type prior: (J^T W^2 J + lam^2 D^2) x = J^T W^2 b (Cheney et al. 1990).
    x_ref = np.linalg.solve(J.T @ W @ W @ J + lam**2 * D @ D, J.T @ W @ W @ b)
    rec = reconstruct(J, b, Tikhonov(lam, noise_weighted=True, normalise=True), noise_std=std)
    np.testing.assert_allclose(np.asarray(rec.image), x_ref, rtol=1e-8)
    # TSVD of W J D^-1 applied to W b, mapped back by D^-1.
    k = 6
    u, s, vt = np.linalg.svd(W @ J @ np.linalg.inv(D), full_matrices=False)
    y = vt[:k].T @ ((u[:, :k].T @ (W @ b)) / s[:k])
    rec = reconstruct(J, b, TSVD(k, noise_weighted=True, normalise=True), noise_std=std)
    np.testing.assert_allclose(np.asarray(rec.image), np.linalg.solve(D, y), rtol=1e-8)
    # Partial NOSER, D = diag(column norms)^0.5 (EIDORS prior_noser's default exponent).
    D5 = np.sqrt(D)
    x_ref = np.linalg.solve(J.T @ W @ W @ J + lam**2 * D5 @ D5, J.T @ W @ W @ b)
    rec = reconstruct(J, b, Tikhonov(lam, noise_weighted=True, normalise=0.5), noise_std=std)
    np.testing.assert_allclose(np.asarray(rec.image), x_ref, rtol=1e-8)
    dec = svd(W @ J, normalise=0.5)
    rec = reconstruct(None, b, TSVD(k, noise_weighted=True, normalise=0.5), noise_std=std,
                      decomposition=dec)
    u, s, vt = np.linalg.svd(W @ J @ np.linalg.inv(D5), full_matrices=False)
    y = vt[:k].T @ ((u[:, :k].T @ (W @ b)) / s[:k])
    np.testing.assert_allclose(np.asarray(rec.image), np.linalg.solve(D5, y), rtol=1e-8)
    with pytest.raises(ValueError, match="normalise"):
        reconstruct(J, b, TSVD(k, normalise=True), decomposition=svd(J))
    with pytest.raises(ValueError, match="normalise"):
        reconstruct(J, b, TSVD(k, normalise=0.5), decomposition=svd(J, normalise=True))
    with pytest.raises(ValueError, match="normalise"):
        Tikhonov(normalise=2.0)
    with pytest.raises(ValueError, match="needs `noise_std`"):
        reconstruct(J, b, TSVD(k, noise_weighted=True))


def test_noise_std_floor():
    v = np.array([1.0, -0.5, 1e-6, 0.0])
    np.testing.assert_allclose(noise_std(v, 0.5), 0.005 * np.abs(v))
    rms = np.sqrt(np.mean(v**2))
    np.testing.assert_allclose(noise_std(v, 0.5, floor=0.1),
                               0.005 * np.maximum(np.abs(v), 0.1 * rms))
    with pytest.raises(ValueError, match="floor"):
        noise_std(v, 0.5, floor=-1)


def test_per_tet_jacobian_warns_and_names_the_grid_path():
    rng = np.random.default_rng(0)
    J = rng.standard_normal((10, 300))  # 30 columns per row: a per-tet Jacobian's shape
    with pytest.warns(UserWarning, match="jacobian_grid"):
        reconstruct(J, J @ rng.standard_normal(300), TSVD(k=3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        reconstruct(J[:, :100], J[:, :100] @ rng.standard_normal(100), TSVD(k=3))  # a grid's shape
