"""Complete electrode model terms and the grounding convention.  [jax]

Complete electrode model (Somersalo, Cheney & Isaacson 1992, SIAM J. Appl. Math. 52:1023;
discretised as in Vauhkonen, Vauhkonen, Savolainen & Kaipio 1999, IEEE TMI 18:2016). With P1
basis functions phi_i, electrodes e_l of contact impedance z_l (Ohm m^2) and injected currents
I_l (A):

    A_M[i, j] = int_Omega sigma grad phi_i . grad phi_j dx + sum_l (1/z_l) int_{e_l} phi_i phi_j dS
    A_Z[i, l] = -(1/z_l) int_{e_l} phi_i dS
    A_D[l, l] = |e_l| / z_l
    [[A_M, A_Z], [A_Z^T, A_D]] [u; U] = [0; I],   sum_l I_l = 0.

The full matrix is symmetric positive semi-definite with the constants (u = c, U = c) as its
null space (A_M 1 + A_Z 1 = 0 row by row, and A_Z^T 1 + A_D 1 = 0).

Grounding (the choice made here): the LAST electrode is the ground during the solve, U_ref = 0,
so its row and column are dropped. The remaining matrix of size n_nodes + n_elec - 1 is symmetric
positive definite (the null space is removed) and keeps the sparsity of the FEM matrix, unlike
the basis change U = N beta, which couples all electrode unknowns. The current at the ground is
the implied -sum of the others. Reported potentials are then shifted so that sum_l U_l = 0 (the
convention of Vauhkonen et al. 1999): the shift is one constant for u and U alike, so every
measured voltage, a difference U_p - U_q, is independent of the ground.

A non-driving electrode carries no current, so its voltage is exactly the mean of u over its
area: from the electrode's row, A_Z[:, l]^T u + A_D[l, l] U_l = 0 gives
U_l = int_{e_l} u dS / |e_l|.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .assembly import TRI_PAIRS, face_areas, face_mass


def reference_electrode(n_elec: int) -> int:
    """The electrode grounded during the solve (the last one)."""
    return n_elec - 1


def cem_entries(n_nodes: int, faces: np.ndarray, face_electrode: np.ndarray,
                n_elec: int) -> tuple[np.ndarray, np.ndarray]:
    """Global (row, column) of every CEM contribution, in `cem_values` order.  [host]

    Arguments:
        n_nodes: number of mesh nodes (electrode l < ref is unknown n_nodes + l).
        faces: (n_eface, 3) node indices of the electrode faces.
        face_electrode: (n_eface,) electrode of each face.
        n_elec: number of electrodes.

    Returns:
        rows, cols: (6 n_eface + 4 n_free,) with n_free the faces not on the ground electrode:
        boundary mass pairs, then A_Z entries, then A_D entries.
    """
    faces = np.asarray(faces, np.int64)
    fe = np.asarray(face_electrode, np.int64)
    free = np.flatnonzero(fe != reference_electrode(n_elec))
    mi, mj = faces[:, TRI_PAIRS[:, 0]].ravel(), faces[:, TRI_PAIRS[:, 1]].ravel()
    eu = n_nodes + fe[free]
    zi, zj = faces[free].ravel(), np.repeat(eu, 3)
    return np.concatenate([mi, zi, eu]), np.concatenate([mj, zj, eu])


def cem_values(nodes_m, faces, face_electrode, free_faces, contact_impedance_ohm_m2):
    """CEM contribution values in `cem_entries` order (SI: S).

    Arguments:
        nodes_m: (n_nodes, 3) node positions in metres.
        faces: (n_eface, 3) electrode faces.
        face_electrode: (n_eface,) electrode of each face.
        free_faces: (n_free,) indices of the faces not on the ground electrode.
        contact_impedance_ohm_m2: (n_elec,) z_l in Ohm m^2.

    Returns:
        (6 n_eface + 4 n_free,) values: (1/z) int phi_a phi_b, -(1/z) int phi_a, |face| / z.
    """
    area = face_areas(nodes_m, faces)
    inv_z = 1.0 / contact_impedance_ohm_m2[face_electrode]
    mass = face_mass(area) * inv_z[:, None]
    a_free, iz_free = area[free_faces], inv_z[free_faces]
    az = jnp.repeat(-(a_free * iz_free) / 3.0, 3)
    ad = a_free * iz_free
    return jnp.concatenate([mass.ravel(), az, ad])


def electrode_rhs(currents, n_nodes: int):
    """Right-hand sides of the grounded system for current patterns.

    Arguments:
        currents: (n_elec, n_pat) injected currents in A (each column sums to zero).
        n_nodes: number of mesh nodes.

    Returns:
        (n_nodes + n_elec - 1, n_pat) right-hand sides (the ground's current is implied).
    """
    n_pat = currents.shape[1]
    return jnp.concatenate([jnp.zeros((n_nodes, n_pat), currents.dtype), currents[:-1]], axis=0)


def split_solution(x, n_nodes: int):
    """Nodal and electrode potentials of a grounded solution, re-referenced to sum_l U_l = 0.

    Arguments:
        x: (n_nodes + n_elec - 1, n_pat) solution of the grounded system (V).
        n_nodes: number of mesh nodes.

    Returns:
        u: (n_nodes, n_pat) nodal potentials (V); U: (n_elec, n_pat) electrode voltages (V),
        both shifted by the same constant so that each column of U sums to zero.
    """
    u = x[:n_nodes]
    U = jnp.concatenate([x[n_nodes:], jnp.zeros((1, x.shape[1]), x.dtype)], axis=0)
    shift = jnp.mean(U, axis=0, keepdims=True)
    return u - shift, U - shift
