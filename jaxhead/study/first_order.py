"""The differentiable counterpart of the sampled study: voltage sensitivity to the normal
displacement of each interface vertex, and first-order propagation of a GRF prior.  [jax + host]

With V(x) the voltages at node positions x and x(d) the morph (`jaxhead.study.morph`), the
sensitivity to interface t's normal displacement at vertex v is

    S_t[r, v] = sum_j dV_r / dx_j . dx_j / dd_v,

dx_j/dd_v = n_v on the vertex itself and E n_v (the harmonic extension) inside. dV/dx comes
by reciprocity (one solve per electrode pair of the protocol, then a reverse pass through the
assembly per row, `node_gradients`), then the chain through the extension is one
multi-right-hand-side solve with K_II on the host (E^T = -K_IB^T K_II^-1).

First order (delta method): dV ~ S_t d with d ~ GP(0, C), so Cov(dV) = S_t C S_t^T; the fitted
conductivities of the reference model, linearised at the truth, move by A dV with
A = (J^T W J)^-1 J^T W (J the (n_rows, 4) tissue Jacobian, W = diag(1 / noise_sd^2)), so
Cov(sigma_hat) = A Cov(dV) A^T. A zero-mean prior gives zero first-order bias; the bias of
a sampled study is then second order (it is what the sampled route measures).

Second order, per sample (`second_order_prediction`): the morph is linear in d (the interface
nodes move by d n, the interior by the fixed linear extension E), so x(d) = x0 + dx with
dx = x(d) - x0 linear in d and no second derivative of the morph; hence

    dV = D V(x0)[dx] + 1/2 D^2 V(x0)[dx, dx] + O(|d|^3),

both directional derivatives along the single direction dx, taken exactly by JAX
forward-over-forward mode (`jax.jvp` of `jax.jvp`) through `simulate(..., nodes=x)`: the
element stiffness's hand-written JVP is itself differentiated, and the sparse solve is a
`jax.lax.custom_linear_solve` whose tangent is another solve with the same matrix, so every
solve reuses one factorisation at x0 (four multi-right-hand-side solves in all).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..fem import ForwardModel, assemble, jacobian, potentials, simulate
from ..fem.solvers import matvec
from ..tissue import Tissue
from .morph import Morph, extension_transpose, morph_nodes


def node_gradients(model: ForwardModel, sigma, protocol, *, chunk_rows: int = 32) -> np.ndarray:
    """dV/dx at the model's nodes by reciprocity: (n_rows, n_nodes, 3) in V/mm.

    With A(x) the grounded CEM matrix, z_p = A^{-1} e_p the field of unit current through
    electrode pair p and row r = (drive d, measurement m, current I), V_r = I z_m^T A z_d, so

        dV_r / dx = -I z_m^T (dA/dx) z_d

    (the geometric counterpart of `jaxhead.fem.jacobian`'s conductivity sensitivity). One solve
    per unique electrode pair of the protocol, then per row one reverse pass through the
    assembly alone (no solve): the row's bilinear form's cotangent on the stored matrix values,
    pulled back to the node positions.

    Arguments:
        model: the reference ForwardModel; sigma: (4,) or (n_tets,) S/m; protocol: its Protocol.
        chunk_rows: rows pulled back together (memory: chunk_rows x (nnz + 3 n_nodes)).
    """
    rows = np.asarray(protocol.rows, dtype=np.int64)
    pairs = np.concatenate([rows[:, :2], rows[:, 2:]])
    lo, hi = pairs.min(1), pairs.max(1)
    sign = np.where(pairs[:, 0] == lo, 1.0, -1.0)
    uniq, index = np.unique(np.stack([lo, hi], 1), axis=0, return_inverse=True)
    index = index.ravel()
    u, U = potentials(model, sigma, uniq, current_a=1.0)  # unit current into lo, out of hi
    u, U = np.asarray(u), np.asarray(U)
    # grounded unknowns (the last electrode is the solve's ground: its voltage is 0)
    z = np.concatenate([u - U[:, -1:], U[:, :-1] - U[:, -1:]], axis=1)
    n = rows.shape[0]
    d_idx, m_idx = index[:n], index[n:]
    scale = -float(protocol.current_a) * sign[:n] * sign[n:]
    sig = jnp.asarray(sigma, dtype=jnp.float64)
    zj = jnp.asarray(z)
    out = np.empty((n, model.n_nodes, 3))
    for s in range(0, n, chunk_rows):
        sl = slice(s, s + chunk_rows)
        out[sl] = np.asarray(_pull_rows(model, sig, zj, jnp.asarray(d_idx[sl]),
                                        jnp.asarray(m_idx[sl]), jnp.asarray(scale[sl])))
    return out


@eqx.filter_jit
def _pull_rows(model, sigma, z, d, m, c):
    """c_r * d(z_{m_r}^T A(x) z_{d_r})/dx at the model's nodes, (len(d), n_nodes, 3)."""
    values0, pull = jax.vjp(lambda x: assemble(model, sigma, nodes=x), model.nodes)
    # cotangent of the bilinear form on the stored values (linear in the values: exact)
    ct = jax.vmap(lambda a, b: jax.grad(lambda v: b @ matvec(model.pattern, v, a))(values0))(
        z[d], z[m])
    return jax.vmap(lambda t: pull(t)[0])(ct * c[:, None])


def displacement_sensitivity(model: ForwardModel, morph: Morph, sigma, protocol, *,
                             tissues=None, node_grad=None) -> dict[Tissue, np.ndarray]:
    """Sensitivity of the voltages to the outward normal displacement of each interface vertex.

    Arguments:
        model: the reference ForwardModel (its nodes are the morph's reference nodes).
        morph: `build_morph(mesh)` of the same mesh.
        sigma: (4,) S/m; protocol: the Protocol.
        tissues: interfaces to compute (default all of the morph's).
        node_grad: optional precomputed `node_gradients(model, sigma, protocol)`.

    Returns:
        {Tissue: (n_rows, n_vertices) dV/dd in V/mm}.
    """
    if not np.array_equal(np.asarray(model.nodes), morph.nodes):
        raise ValueError("`model` and `morph` were built from different meshes; build both from "
                         "the reference TetMesh.")
    G = node_gradients(model, sigma, protocol) if node_grad is None else np.asarray(node_grad)
    n_rows = G.shape[0]
    # total derivative w.r.t. the interface nodes' positions: direct + through the extension
    gi = G[:, morph.free, :].transpose(1, 0, 2).reshape(len(morph.free), -1)
    gb = G[:, morph.fixed, :] + extension_transpose(morph, gi).reshape(
        len(morph.fixed), n_rows, 3).transpose(1, 0, 2)
    pos = np.full(morph.nodes.shape[0], -1, np.int64)
    pos[morph.fixed] = np.arange(morph.fixed.size)
    keys = morph.interfaces if tissues is None else [Tissue.parse(t) for t in tissues]
    out = {}
    for t in keys:
        s = morph.interface(t)
        out[Tissue.parse(t)] = np.einsum("rvk,vk->rv", gb[:, pos[s.vertices], :], s.normals)
    return out


def voltage_covariance(S: np.ndarray, points, sd_mm: float, correlation_mm: float, *,
                       block: int = 2048) -> np.ndarray:
    """First-order Cov(dV) = S C S^T for a squared-exponential GRF prior, (n_rows, n_rows) V^2.

    Arguments:
        S: (n_rows, n_v) sensitivity of one interface (V/mm); points: (n_v, 3) its vertices (mm).
        sd_mm, correlation_mm: the prior (as `sample_grf`).
        block: rows of C formed at a time (memory block x n_v).
    """
    p = np.asarray(points, dtype=np.float64)
    S = np.asarray(S, dtype=np.float64)
    if S.shape[1] != p.shape[0]:
        raise ValueError(f"`S` has {S.shape[1]} columns but there are {p.shape[0]} points.")
    out = np.zeros((S.shape[0], S.shape[0]))
    for i in range(0, p.shape[0], block):
        sq_i = np.sum(p[i:i + block] ** 2, 1)
        d2 = np.maximum(sq_i[:, None] + np.sum(p * p, 1)[None, :] - 2 * p[i:i + block] @ p.T, 0)
        C = sd_mm**2 * np.exp(-d2 / (2 * correlation_mm**2))
        out += S[:, i:i + block] @ (C @ S.T)
    return out


def fit_map(model: ForwardModel, sigma, protocol, noise_sd) -> np.ndarray:
    """Linearised weighted least-squares map A (4, n_rows): d sigma_hat = A dV (S/m per V)."""
    J = np.asarray(jacobian(model, np.asarray(sigma, np.float64), protocol, per="tissue"))
    W = 1.0 / np.asarray(noise_sd) ** 2
    JtW = J.T * W
    return np.linalg.solve(JtW @ J, JtW)


def first_order_summary(S: np.ndarray, points, sd_mm: float, correlation_mm: float, volts,
                        noise_sd, A=None, sigma=None) -> dict:
    """First-order predictions of a GRF study of one interface.

    Returns a dict: rms_rel_voltage_change (sqrt(trace Cov) / ||V||, the RMS of the sampled
    rel_voltage_change to first order), rms_change_over_noise (sqrt(mean diag(Cov) / noise^2)),
    effective_dof (trace(Cov)^2 / trace(Cov^2): ||dV||^2 is a sum of weighted chi^2 variables
    with variance 2 trace(Cov^2), so the RMS of n independent samples scatters around the
    prediction by a relative sd of about sqrt(1 / (2 n effective_dof))), and, with A and sigma,
    sigma_sd_percent_<tissue> (first-order sd of the fitted conductivities in % of the truth).
    """
    cov = voltage_covariance(S, points, sd_mm, correlation_mm)
    v = np.asarray(volts)
    tr2 = float(np.sum(cov * cov))  # trace(Cov^2), Cov symmetric
    out = {"rms_rel_voltage_change": float(np.sqrt(np.trace(cov)) / np.linalg.norm(v)),
           "effective_dof": float(np.trace(cov) ** 2 / tr2) if tr2 > 0 else float("nan"),
           "rms_change_over_noise": float(np.sqrt(np.mean(np.diag(cov) / np.asarray(noise_sd) ** 2)))}
    if A is not None:
        cs = A @ cov @ A.T
        for i, t in enumerate(("brain", "csf", "skull", "scalp")):
            out[f"sigma_sd_percent_{t}"] = float(100 * np.sqrt(max(cs[i, i], 0)) / sigma[i])
    return out


def linear_prediction(S: np.ndarray, d) -> np.ndarray:
    """First-order voltage change S d (n_rows,) of a displacement d (n_v,) mm."""
    return np.asarray(S) @ np.asarray(d)


@eqx.filter_jit
def _taylor2(model, sigma, protocol, x0, dx):
    """(D V(x0)[dx], D^2 V(x0)[dx, dx]) by forward-over-forward mode along dx."""
    def first(x):
        return jax.jvp(lambda y: simulate(model, sigma, protocol, nodes=y), (x,), (dx,))[1]

    return jax.jvp(first, (x0,), (dx,))


def taylor_terms(model: ForwardModel, sigma, protocol, dx) -> tuple[np.ndarray, np.ndarray]:
    """First and second directional derivatives of the voltages along a node displacement.

    Arguments:
        model: the reference ForwardModel (expanded about its own nodes x0).
        sigma: (4,) or (n_tets,) S/m; protocol: the Protocol (concrete rows).
        dx: (n_nodes, 3) node displacement in mm.

    Returns:
        (D V(x0)[dx], D^2 V(x0)[dx, dx]), each (n_rows,) in V; V(x0 + dx) - V(x0) =
        first + second / 2 + O(|dx|^3).
    """
    dx = np.asarray(dx, dtype=np.float64)
    if dx.shape != (model.n_nodes, 3):
        raise ValueError(f"`dx` has shape {dx.shape}; pass one displacement per node, "
                         f"({model.n_nodes}, 3) in mm.")
    if not np.all(np.isfinite(dx)):
        raise ValueError("`dx` contains NaN or Inf; pass finite node displacements in mm.")
    d1, d2 = _taylor2(model, jnp.asarray(sigma, dtype=jnp.float64), protocol,
                      jnp.asarray(model.nodes, dtype=jnp.float64), jnp.asarray(dx))
    return np.asarray(d1), np.asarray(d2)


def second_order_prediction(model: ForwardModel, morph: Morph, sigma, protocol, d,
                            tissue) -> dict[str, np.ndarray]:
    """Voltage change of a morph to second order in the normal displacement d of one interface.

    dV(d) = V(x(d)) - V(x0) ~ S d + 1/2 D^2 V(x0)[dx, dx], dx = x(d) - x0 the morph's node
    displacement (exactly linear in d: no second derivative of the morph enters).

    Arguments:
        model: the reference ForwardModel; morph: `build_morph` of the same mesh.
        sigma: (4,) or (n_tets,) S/m; protocol: the Protocol.
        d: (n_vertices,) normal displacement of the interface's vertices in mm (outward).
        tissue: the interface (a Tissue or its name).

    Returns:
        {"first": S d, "second": 1/2 D^2 V[dx, dx], "prediction": their sum}, each (n_rows,) V.
        The first term equals `displacement_sensitivity(...)[tissue] @ d` (here by forward mode).
    """
    if not np.array_equal(np.asarray(model.nodes), morph.nodes):
        raise ValueError("`model` and `morph` were built from different meshes; build both from "
                         "the reference TetMesh.")
    dx = np.asarray(morph_nodes(morph, {tissue: d})) - morph.nodes
    first, second = taylor_terms(model, sigma, protocol, dx)
    return {"first": first, "second": 0.5 * second, "prediction": first + 0.5 * second}
