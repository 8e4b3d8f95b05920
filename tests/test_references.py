"""Checks of the analytic sphere references in tests/references.py against closed forms,
quadrature and the PDE itself (Laplace equation, interface and boundary conditions)."""

import numpy as np
import pytest

from references import (
    cap_factor,
    homogeneous_sphere_potential,
    legendre_table,
    mag,
    rdm,
    shell_sphere_potential,
)

R = 0.096
RADII = np.array([0.080, 0.084, 0.090, 0.096])
SIGMA = np.array([0.3, 1.79, 0.018, 0.44])  # brain, CSF, skull, scalp (tissue.py sources)
SRC = np.array([0.0, 0.3, 1.0])
SNK = np.array([0.8, -0.2, 0.1])
I = 1e-3


def _random_points(n, rmin, rmax, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(rmin, rmax, size=(n, 1))


def _cap_quadrature(centre, halfangle, n_t=24, n_phi=48):
    """Gauss-Legendre in cos(theta) x uniform in phi over a cap: unit directions, weights
    summing to 1 (exact for polynomials in the cap's coordinates up to high degree)."""
    c = _unit(centre)
    e1 = np.cross(c, [1.0, 0, 0] if abs(c[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(c, e1)
    x, w = np.polynomial.legendre.leggauss(n_t)
    ct = np.cos(halfangle) + (1 - np.cos(halfangle)) * (x + 1) / 2
    st = np.sqrt(1 - ct**2)
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    d = (ct[:, None, None] * c + st[:, None, None] * (np.cos(phi)[None, :, None] * e1
                                                      + np.sin(phi)[None, :, None] * e2))
    wt = np.repeat(w[:, None] / 2 / n_phi, n_phi, axis=1)
    return d.reshape(-1, 3), wt.ravel()


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def test_legendre_table_matches_numpy():
    t = np.linspace(-1, 1, 7)
    p = legendre_table(t, 12)
    for n in range(13):
        ref = np.polynomial.legendre.legval(t, np.eye(13)[n])
        np.testing.assert_allclose(p[n], ref, atol=1e-13)


def test_surface_closed_form_matches_series_sum():
    # REFERENCES.md: sum (2n+1)/n P_n(t) = 2/sqrt(2-2t) - 2 + ln(2/(1 - t + sqrt(2-2t))); the
    # series at s = r/R < 1 converges geometrically, and s -> 1 gives the surface formula.
    t = np.array([-0.9, -0.3, 0.2, 0.7])
    x = np.c_[np.sqrt(1 - t**2), np.zeros(4), t] * R
    u = homogeneous_sphere_potential(x, R, 1.0, [0, 0, 1.0], [0, 0, -1.0], 4 * np.pi * R)
    f = lambda tt: 2 / np.sqrt(2 - 2 * tt) - 2 + np.log(2 / (1 - tt + np.sqrt(2 - 2 * tt)))
    np.testing.assert_allclose(u, f(t) - f(-t), rtol=1e-12)


def test_one_shell_series_equals_closed_form():
    # plain series (no Kummer acceleration) at r <= 0.9 R: terms ~ 0.9^n, 600 terms -> 1e-27
    x = _random_points(40, 0.05 * R, 0.9 * R)
    u_series = shell_sphere_potential(x, [R], [0.33], SRC, SNK, I, n_terms=600, accelerate=False)
    u_closed = homogeneous_sphere_potential(x, R, 0.33, SRC, SNK, I)
    np.testing.assert_allclose(u_series, u_closed, rtol=1e-10, atol=1e-12 * np.abs(u_closed).max())


def test_equal_shells_equal_homogeneous():
    x = np.r_[_random_points(30, 0.0, 0.9 * R, seed=1), _random_points(10, R, R, seed=2)]
    u4 = shell_sphere_potential(x, RADII, [0.5] * 4, SRC, SNK, I, n_terms=400)
    u1 = homogeneous_sphere_potential(x, R, 0.5, SRC, SNK, I)
    np.testing.assert_allclose(u4, u1, rtol=1e-10, atol=1e-12 * np.abs(u1).max())


def test_acceleration_does_not_change_the_sum():
    # interior points, where the plain series converges geometrically too
    x = _random_points(30, 0.1 * R, 0.93 * R, seed=3)
    a = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=700, accelerate=False)
    b = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=700, accelerate=True)
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.abs(a).max())


def test_surface_series_converged():
    # accelerated series on the surface: 200 and 400 terms agree (geometric convergence)
    x = _random_points(10, R, R, seed=4)
    a = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=200)
    b = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=400)
    np.testing.assert_allclose(a, b, rtol=1e-10)


@pytest.mark.parametrize("k", range(4))
def test_laplace_equation_inside_each_shell(k):
    # 7-point finite-difference Laplacian at mid-shell points: truncation h^2 u''''/12 with
    # h = 0.1 mm and u varying on the ~cm scale gives |lap u| << sum |u_ii| (1e-4 relative).
    lo = 0.0 if k == 0 else RADII[k - 1]
    rmid = 0.5 * (lo + RADII[k]) if k else 0.6 * RADII[0]
    x0 = _random_points(6, rmid, rmid, seed=10 + k)
    h = 1e-4
    f = lambda p: shell_sphere_potential(p, RADII, SIGMA, SRC, SNK, I, n_terms=300,
                                         cap_halfangle=0.05)
    u0 = f(x0)
    lap = np.zeros(len(x0))
    scale = np.zeros(len(x0))
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        d2 = (f(x0 + e) - 2 * u0 + f(x0 - e)) / h**2
        lap += d2
        scale += np.abs(d2)
    assert np.all(np.abs(lap) < 1e-4 * scale), (lap, scale)


@pytest.mark.parametrize("k", range(3))
def test_interface_continuity(k):
    # u and sigma du/dr continuous at r_k: second-order one-sided differences (error ~ d^2 u''')
    a = RADII[k]
    d = _random_points(5, 1.0, 1.0, seed=20 + k)
    f = lambda r: shell_sphere_potential(d * r, RADII, SIGMA, SRC, SNK, I, n_terms=400,
                                         cap_halfangle=0.05)
    dr = 2e-5
    u_in, u_out = f(a * (1 - 1e-12)), f(a * (1 + 1e-12))
    np.testing.assert_allclose(u_in, u_out, rtol=1e-8, atol=1e-10 * np.abs(u_in).max())
    g_in = (3 * f(a) - 4 * f(a - dr) + f(a - 2 * dr)) / (2 * dr)
    g_out = (-3 * f(a) + 4 * f(a + dr) - f(a + 2 * dr)) / (2 * dr)
    j_in, j_out = SIGMA[k] * g_in, SIGMA[k + 1] * g_out
    np.testing.assert_allclose(j_in, j_out, rtol=2e-3, atol=2e-3 * np.abs(j_in).max())
    # and the conductivity jump really makes the slopes differ
    assert np.max(np.abs(g_in - g_out)) > 0.1 * np.max(np.abs(g_in))


def test_cap_tends_to_point():
    x = _random_points(20, 0.2 * R, 0.85 * R, seed=5)
    up = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=400, accelerate=False)
    errs = []
    for alpha in (0.08, 0.04, 0.02):
        uc = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=400, cap_halfangle=alpha)
        errs.append(np.abs(uc - up).max() / np.abs(up).max())
    # the cap's first moment vanishes by symmetry, so the error is O(alpha^2): ratio ~4
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 1.8), (errs, rates)
    assert errs[-1] < 1e-3


def test_cap_equals_quadrature_of_point_sources():
    # the cap factor against brute force: average the closed-form point-source potential over
    # source and sink caps (quadrature exact to ~1e-10 for the smooth integrand at r <= 0.8 R)
    alpha = 0.15
    x = _random_points(8, 0.2 * R, 0.8 * R, seed=6)
    ds, w = _cap_quadrature(SRC, alpha)
    dk, _ = _cap_quadrature(SNK, alpha)
    ref = np.zeros(len(x))
    for a, b, wi in zip(ds, dk, w):
        ref += wi * homogeneous_sphere_potential(x, R, 0.4, a, b, I)
    u = shell_sphere_potential(x, [R], [0.4], SRC, SNK, I, n_terms=600, cap_halfangle=alpha)
    np.testing.assert_allclose(u, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())


def test_average_halfangle_is_mean_over_cap():
    # electrode voltage = mean potential under the electrode: compare with quadrature of the
    # multi-shell surface potential (cap sources keep it smooth away from the drive caps)
    beta = 0.06
    centres = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.2], [-0.5, 0.5, -0.6]])
    u = shell_sphere_potential(centres * R / np.linalg.norm(centres, axis=1, keepdims=True),
                               RADII, SIGMA, SRC, SNK, I, n_terms=1500, cap_halfangle=0.05,
                               average_halfangle=beta)
    for c, ui in zip(centres, u):
        d, w = _cap_quadrature(c, beta, n_t=16, n_phi=32)
        vals = shell_sphere_potential(d * R, RADII, SIGMA, SRC, SNK, I, n_terms=1500,
                                      cap_halfangle=0.05)
        assert abs(w @ vals - ui) < 1e-6 * np.abs(u).max()


def test_cap_factor_limits():
    n = np.arange(1, 50)
    np.testing.assert_allclose(cap_factor(n, None), 1.0)
    np.testing.assert_allclose(cap_factor(n, 1e-4), 1.0, atol=1e-4)
    # hemisphere: mean of P_n over the upper half, (P_{n-1}(0) - P_{n+1}(0)) / (2n+1)
    np.testing.assert_allclose(cap_factor(np.array([1]), np.pi / 2), [0.5])


def test_rdm_mag():
    a = np.array([1.0, -2.0, 3.0])
    assert rdm(a, 5 * a) == pytest.approx(0.0, abs=1e-15)
    assert rdm(a, -a) == pytest.approx(2.0)
    assert mag(a, np.e * a) == pytest.approx(1.0)
    assert mag(a, a) == 0.0
    b = a + np.array([0.1, 0, 0])
    assert 0 < rdm(a, b) < 0.1


def test_per_point_and_per_electrode_caps():
    # arrays of equal angles give the scalar result; a pair (a, a) equals a
    x = _random_points(5, R, R, seed=7)
    a = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=300, cap_halfangle=0.05,
                               average_halfangle=0.04)
    b = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=300,
                               cap_halfangle=(0.05, 0.05), average_halfangle=np.full(5, 0.04))
    np.testing.assert_allclose(a, b, rtol=1e-13)
    # linearity: (source cap 0.03, sink cap 0.07) = (source -> far) + (far -> sink), the
    # two contributions of the far electrode (same cap) cancelling
    c = shell_sphere_potential(x, RADII, SIGMA, SRC, SNK, I, n_terms=300,
                               cap_halfangle=(0.03, 0.07))
    far = np.array([0.1, 0.2, -1.0])
    s1 = shell_sphere_potential(x, RADII, SIGMA, SRC, far, I, n_terms=300,
                                cap_halfangle=(0.03, 0.07))
    s2 = shell_sphere_potential(x, RADII, SIGMA, far, SNK, I, n_terms=300,
                                cap_halfangle=(0.07, 0.07))
    np.testing.assert_allclose(c, s1 + s2, rtol=1e-10, atol=1e-12 * np.abs(c).max())
