"""Simulated difference data: a spherical conductivity perturbation and the voltage change it makes."""

import numpy as np

from ..fem import simulate
from ..tissue import Tissue
from .noise import add_noise


def simulate_difference(model, sigma_ref, sigma_pert, protocol, *, noise_percent: float = 0.0,
                        seed: int = 0):
    """Difference data of a conductivity change, optionally with noise per channel.

    To avoid the inverse crime (Kaipio & Somersalo 2005, sec. 1.2: data simulated with the very
    model that inverts them hide the modelling error), simulate on a finer mesh than the
    reconstruction mesh: place electrodes at the same positions with the same radius on both
    meshes, perturb the fine mesh's conductivity (e.g. `spherical_perturbation(fine_mesh, ...)`),
    call this with the fine model, and reconstruct with the coarse model's Jacobian. The data
    vector lines up with the coarse model's rows because both use the same `protocol`.

    Arguments:
        model: the ForwardModel that simulates the data (the fine one).
        sigma_ref, sigma_pert: (4,) or (n_tets,) conductivities of the model in S/m, before
            and after the change.
        protocol: the Protocol (same electrode order as the reconstruction model).
        noise_percent: Gaussian noise in % of each channel's baseline voltage (the seed paper's
            0.5 %), added to the difference (`add_noise(dv, noise_percent, reference=v_ref)`).
        seed: noise seed.

    Returns:
        dv: (n_rows,) voltage change in V (noisy when noise_percent > 0); v_ref: (n_rows,)
        baseline voltages in V (noise-free; `noise_std(v_ref, noise_percent)` is the noise level).
    """

    if noise_percent < 0:
        raise ValueError(f"`noise_percent` must be >= 0, got {noise_percent}.")
    v_ref = np.asarray(simulate(model, sigma_ref, protocol))
    dv = np.asarray(simulate(model, sigma_pert, protocol)) - v_ref
    if noise_percent > 0:
        dv = add_noise(dv, noise_percent, seed=seed, reference=v_ref)
    return dv, v_ref


# --- simulation helpers -------------------------------------------------------------------------


def spherical_perturbation(mesh, sigma_tet, centre_mm, radius_mm: float, rel_change: float,
                           *, tissue=None) -> np.ndarray:
    """Per-tet conductivity with a spherical change: sigma * (1 + rel_change) inside the ball.

    Arguments:
        mesh: a `TetMesh`.
        sigma_tet: (n_tets,) baseline conductivity (S/m).
        centre_mm: (3,) ball centre in world mm.
        radius_mm: ball radius in mm (tets whose centroid lies inside change).
        rel_change: relative change, e.g. 0.1 for +10 %.
        tissue: restrict the change to one tissue (e.g. "brain"); None changes any tissue.

    Returns:
        (n_tets,) perturbed conductivity.
    """

    sigma_tet = np.asarray(sigma_tet, dtype=np.float64)
    if sigma_tet.shape != (mesh.n_tets,):
        raise ValueError(f"`sigma_tet` has shape {sigma_tet.shape}; pass one value per tet ({mesh.n_tets}).")
    if not radius_mm > 0:
        raise ValueError(f"`radius_mm` must be > 0, got {radius_mm}.")
    if not rel_change > -1:
        raise ValueError(f"`rel_change` must be > -1 (conductivity stays positive), got {rel_change}.")
    inside = perturbation_mask(mesh, centre_mm, radius_mm, tissue=tissue)
    if not inside.any():
        where = "" if tissue is None else f" {Tissue.parse(tissue).name}"
        raise ValueError(f"no{where} tet centroid lies within {radius_mm} mm of {list(centre_mm)}; "
                         "move the centre or enlarge the radius.")
    out = sigma_tet.copy()
    out[inside] *= 1.0 + rel_change
    return out


def perturbation_mask(mesh, centre_mm, radius_mm: float, *, tissue=None) -> np.ndarray:
    """Boolean (n_tets,) mask of tets whose centroid lies inside the ball (and tissue)."""

    c = np.asarray(centre_mm, dtype=np.float64)
    if c.shape != (3,):
        raise ValueError(f"`centre_mm` must be 3 coordinates, got shape {c.shape}.")
    inside = np.linalg.norm(mesh.centroids() - c, axis=1) <= radius_mm
    if tissue is not None:
        inside &= mesh.labels == int(Tissue.parse(tissue))
    return inside
