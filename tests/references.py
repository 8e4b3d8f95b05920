"""Analytic references for the forward model: potentials in concentric-shell spheres.  [numpy]

Everything here is plain NumPy in SI units (metres, S/m, A, V), independent of jaxhead.

A current `current` A enters the outer surface (radius R = radii[-1]) at direction `source`
and leaves at `sink`, either at points or spread uniformly over spherical caps of half-angle
`cap_halfangle`. In each shell k the degree-n part of the potential is
(A_k r^n + B_k r^-(n+1)) P_n(cos gamma), B = 0 in the core, with continuity of u and of
sigma du/dr at every interface and sigma du/dr = j on the outer surface (Rush & Driscoll 1968,
IEEE TBME 15:8; the same recursion as de Munck 1988, J. Appl. Phys. 64:464). The constant
(n = 0) term is dropped, so the potential has zero mean over the outer surface.

The recursion is written in ratios that never overflow: the radial "admittance"
y(r) = sigma u'(r) / u(r) of each degree is carried outwards and the potential inwards, with
powers (a/r)^(2n+1) <= 1 only.
"""

from __future__ import annotations

import numpy as np


def legendre_table(t: np.ndarray, n_max: int) -> np.ndarray:
    """P_0..P_n_max at t by Bonnet's recursion, shape (n_max + 1, *t.shape)."""
    t = np.asarray(t, dtype=np.float64)
    p = np.empty((n_max + 1,) + t.shape)
    p[0] = 1.0
    if n_max >= 1:
        p[1] = t
    for n in range(1, n_max):
        p[n + 1] = ((2 * n + 1) * t * p[n] - n * p[n - 1]) / (n + 1)
    return p


def cap_factor(n: np.ndarray, halfangle: float | None) -> np.ndarray:
    """Degree-n factor of a uniform density over a cap: the mean of P_n over the cap.

    (P_{n-1}(cos a) - P_{n+1}(cos a)) / ((2n+1)(1 - cos a)); 1 for a point (halfangle None/0).
    `halfangle` may be an array: the result has shape n.shape + halfangle.shape.
    By the Funk-Hecke theorem the same factor turns a point value of a degree-n zonal
    harmonic into its mean over a cap centred there.
    """
    n = np.asarray(n)
    if halfangle is None:
        return np.ones(n.shape)
    a = np.asarray(halfangle, dtype=np.float64)
    c = np.cos(a)
    p = legendre_table(c, int(n.max()) + 1)  # (n_max + 2, *a.shape)
    nn = n.reshape(n.shape + (1,) * a.ndim)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = (p[n - 1] - p[n + 1]) / ((2 * nn + 1) * (1.0 - c))
    return np.where(a == 0.0, 1.0, f)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def radial_profiles(r: np.ndarray, radii, sigmas, n: np.ndarray) -> np.ndarray:
    """g_n(r) = u_n(r) / u_n(R) for each point radius and degree, shape (len(n), len(r)).

    """
    radii = np.asarray(radii, dtype=np.float64)
    sigmas = np.asarray(sigmas, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)[:, None]
    beta, _ = _shell_ratios(radii, sigmas, n)
    K = radii.size
    shell = np.minimum(np.searchsorted(radii, r, side="left"), K - 1)
    g = np.ones((n.shape[0], r.size))
    inner = np.r_[0.0, radii[:-1]]

    def h_ratio(k, ra, rb):
        """h_k(ra) / h_k(rb) for ra <= rb in shell k, h_k = r^n (1 + beta_k (a/r)^(2n+1))."""
        a = inner[k]
        with np.errstate(divide="ignore", invalid="ignore"):
            pa = np.where(ra > 0, (ra / rb) ** n, np.where(n == 0, 1.0, 0.0))
        if k == 0:
            return pa
        sa = beta[k] * (a / ra) ** (2 * n + 1)
        sb = beta[k] * (a / rb) ** (2 * n + 1)
        return pa * (1.0 + sa) / (1.0 + sb)

    for k in range(K):
        sel = shell == k
        if not sel.any():
            continue
        gk = h_ratio(k, r[sel][None, :], radii[k])
        for m in range(k + 1, K):
            gk = gk * h_ratio(m, inner[m], radii[m])
        g[:, sel] = gk
    return g


def _shell_ratios(radii, sigmas, n):
    """beta_k (shell k's B/A ratio scaled at its inner radius) and y_k at each outer radius."""
    K = radii.size
    beta = [np.zeros_like(n)]
    y = sigmas[0] * n / radii[0]
    ys = [y]
    for k in range(1, K):
        a, s = radii[k - 1], sigmas[k]
        b = (s * n / a - y) / (y + s * (n + 1) / a)
        q = b * (a / radii[k]) ** (2 * n + 1)
        y = s * (n - (n + 1) * q) / (radii[k] * (1.0 + q))
        beta.append(b)
        ys.append(y)
    return beta, ys


def outer_admittance(radii, sigmas, n: np.ndarray) -> np.ndarray:
    """y_n(R) = sigma_K u_n'(R) / u_n(R) in S/m^2, shape (len(n),)."""
    n = np.asarray(n, dtype=np.float64)
    _, ys = _shell_ratios(np.asarray(radii, float), np.asarray(sigmas, float), n)
    return ys[-1]


def shell_sphere_potential(points, radii, sigmas, source, sink, current: float = 1.0, *,
                           n_terms: int = 2000, cap_halfangle: float | None = None,
                           average_halfangle: float | None = None,
                           accelerate: bool = True) -> np.ndarray:
    """Potential of a multi-shell sphere driven through its outer surface (Legendre series).

    Arguments:
        points: (k, 3) evaluation points in m, |x| <= R.
        radii: (K,) increasing outer radii of the shells in m (K = 1: homogeneous sphere).
        sigmas: (K,) conductivities in S/m, inside out.
        source, sink: (3,) directions (or surface points) where current enters and leaves.
        current: injected current in A.
        n_terms: highest Legendre degree.
        cap_halfangle: uniform current over caps of this half-angle (rad) instead of points;
            one value or (source, sink).
        average_halfangle: return the mean of u over the cap of this half-angle centred on
            each point's direction (points on the outer surface: electrode voltages of
            non-driving electrodes, which in the complete electrode model equal the mean
            potential under them); one value or one per point.
        accelerate: for point electrodes, sum the series as the closed-form homogeneous
            sphere (outer conductivity) plus the difference series, which converges
            geometrically even on the surface (False: the plain series, for tests).

    Returns:
        (k,) potentials in V (zero mean over the outer surface).
    """
    radii = np.atleast_1d(np.asarray(radii, dtype=np.float64))
    sigmas = np.atleast_1d(np.asarray(sigmas, dtype=np.float64))
    if radii.shape != sigmas.shape or np.any(np.diff(radii) <= 0):
        raise ValueError("radii must increase and match sigmas in length")
    x = np.atleast_2d(np.asarray(points, dtype=np.float64))
    R = radii[-1]
    r = np.linalg.norm(x, axis=1)
    if np.any(r > R * (1 + 1e-9)):
        raise ValueError("points must lie inside the sphere")
    n = np.arange(1, n_terms + 1)
    caps = (None, None) if cap_halfangle is None else np.broadcast_to(
        np.asarray(cap_halfangle, dtype=np.float64), (2,))
    un_R = current * (2 * n + 1) / (4 * np.pi * R**2) / outer_admittance(radii, sigmas, n)
    g = radial_profiles(r, radii, sigmas, n) * un_R[:, None]  # (N, k) degree-n potentials
    if average_halfangle is not None:
        avg = np.broadcast_to(np.asarray(average_halfangle, dtype=np.float64), (len(x),))
        g = g * cap_factor(n, avg)
    out = np.zeros(len(x))
    point = (cap_halfangle is None or np.all(np.asarray(cap_halfangle) == 0.0)) and (
        average_halfangle is None or np.all(np.asarray(average_halfangle) == 0.0))
    if point and accelerate:
        # Kummer's transformation: subtract the homogeneous sphere of the outer conductivity,
        # known in closed form. The remaining degree-n terms decay like (R_{K-1}/R)^(2n+1) in
        # the outer shell and like (r/R)^n inside, instead of like n^(-1/2) on the surface.
        out += homogeneous_sphere_potential(x, R, sigmas[-1], source, sink, current)
        g = g - (current * (2 * n + 1) / (4 * np.pi * sigmas[-1] * R * n))[:, None] * (
            (r / R)[None, :] ** n[:, None])
    xd = np.where(r[:, None] > 0, x, np.array([0.0, 0.0, 1.0]))
    xd = _unit(xd)
    for d, sign, cap in ((_unit(source), 1.0, caps[0]), (_unit(sink), -1.0, caps[1])):
        t = np.clip(xd @ d, -1.0, 1.0)
        p = legendre_table(t, n_terms)[1:]  # (N, k)
        out += sign * np.einsum("n,nk,nk->k", cap_factor(n, cap), g, p)
    return out


def homogeneous_sphere_potential(points, radius: float, sigma: float, source, sink,
                                 current: float = 1.0) -> np.ndarray:
    """Closed-form potential of point currents on a homogeneous sphere, any |x| <= R.

    With s = r/R, t = cos(angle to the electrode) and D = sqrt(1 - 2 s t + s^2), the series
    I/(4 pi sigma R) sum_{n>=1} (2n+1)/n s^n P_n(t) sums to
    I/(4 pi sigma R) [2/D - 2 + ln(2 / (1 - s t + D))] (generating function of P_n and its
    integral; at s = 1 this is the surface formula of REFERENCES.md). Same gauge as
    `shell_sphere_potential` (zero mean on the surface). In m, S/m, A -> V.
    """
    x = np.atleast_2d(np.asarray(points, dtype=np.float64))
    r = np.linalg.norm(x, axis=1)
    s = r / radius
    xd = _unit(np.where(r[:, None] > 0, x, np.array([0.0, 0.0, 1.0])))
    out = np.zeros(len(x))
    for d, sign in ((_unit(source), 1.0), (_unit(sink), -1.0)):
        t = np.clip(xd @ d, -1.0, 1.0)
        D = np.sqrt(np.maximum(1.0 - 2.0 * s * t + s * s, 0.0))
        out += sign * (2.0 / D - 2.0 + np.log(2.0 / (1.0 - s * t + D)))
    return current / (4.0 * np.pi * sigma * radius) * out


def rdm(a, b) -> float:
    """Relative difference measure, || a/|a| - b/|b| || (0..2; SimNIBS tests, Meijs 1989)."""
    a, b = np.ravel(a), np.ravel(b)
    return float(np.linalg.norm(a / np.linalg.norm(a) - b / np.linalg.norm(b)))


def mag(a, b) -> float:
    """Magnitude error, |ln(|a| / |b|)| (SimNIBS tests)."""
    return float(abs(np.log(np.linalg.norm(np.ravel(a)) / np.linalg.norm(np.ravel(b)))))
