"""Perturbation models of a label map and of electrode positions, each seeded and described.  [host]

Every function takes a LabelMap of nested tissues (0 background, 1 BRAIN, 2 CSF, 3 SKULL,
4 SCALP) and returns (LabelMap, description): the description is a JSON-able dict that names the
model, its parameters, seed and how many voxels changed, so a study's output says what was done
(as the UCL Mesher deformation scripts record theirs). The perturbed map then goes through the
library's own route (make_layers -> extract_surfaces -> tetrahedralize), which restores nesting
and minimum thicknesses and reports what it changed.

Distances are Euclidean in mm (`scipy.ndimage.distance_transform_edt` with the voxel sizes), so
the models do not depend on the voxel size beyond the grid's resolution.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..electrodes import Electrodes, place_electrodes
from ..geometry import TetMesh
from ..tissue import Tissue
from ..volume import LabelMap, voxel_sizes

#: Label-map perturbation kinds (the re-mesh route) and what their amplitude means.
LABEL_KINDS = {
    "none": "ignored: the unperturbed map re-meshed, the route's own noise floor (meshing "
            "differences alone)",
    "dilate": "voxels the tissue's outer interface moves outward (k >= 1)",
    "erode": "voxels the tissue's outer interface moves inward (k >= 1)",
    "skull_scale": "factor on the skull's local thickness (> 0; 1 = unchanged)",
    "csf_scale": "factor on the CSF's local thickness (>= 0; 0 removes the CSF, brain fills it)",
    "skull_hole": "radius in mm of a hole opened through the skull (> 0), filled with scalp",
    "skull_close": "closing radius in mm filling skull openings (> 0)",
}


def _check(labels: LabelMap) -> np.ndarray:
    if not isinstance(labels, LabelMap):
        raise ValueError(f"`labels` must be a jaxhead LabelMap, got {type(labels).__name__}.")
    return np.asarray(labels.labels).astype(np.int64)


def _edt(mask: np.ndarray, spacing) -> np.ndarray:
    """Distance in mm from every voxel outside `mask` to the nearest voxel of `mask` (0 inside)."""
    if not mask.any():
        return np.full(mask.shape, np.inf)
    return ndimage.distance_transform_edt(~mask, sampling=spacing)


def _out(labels: LabelMap, new: np.ndarray, old: np.ndarray, desc: dict):
    desc["voxels_changed"] = int((new != old).sum())
    return LabelMap(new.astype(np.uint8), labels.affine), desc


def dilate_erode(labels: LabelMap, tissue, k: int) -> tuple[LabelMap, dict]:
    """Move a tissue's outer interface by k voxels (k > 0 out, k < 0 in; 6-connected steps).

    Dilation: voxels of outer tissues within k steps of the solid of tissues <= t become t (for
    SCALP also background voxels). Erosion: voxels of t within k steps of the outside of that
    solid become the next outer tissue (background for SCALP).
    """
    L = _check(labels)
    t = int(Tissue.parse(tissue))
    if t < 1:
        raise ValueError("`tissue` must be brain, csf, skull or scalp, not background.")
    if int(k) != k or k == 0:
        raise ValueError(f"`k` must be a non-zero integer number of voxels, got {k}.")
    k = int(k)
    solid = (L >= 1) & (L <= t)
    st = ndimage.generate_binary_structure(3, 1)
    new = L.copy()
    if k > 0:
        grown = ndimage.binary_dilation(solid, st, iterations=k)
        target = grown & ~solid & ((L > t) | ((L == 0) & (t == 4)))
        new[target] = t
    else:
        shrunk = ndimage.binary_erosion(solid, st, iterations=-k, border_value=0)
        new[solid & ~shrunk & (L == t)] = t + 1 if t < 4 else 0
    return _out(labels, new, L, {"kind": "dilate" if k > 0 else "erode",
                                 "tissue": Tissue(t).name.lower(), "k_voxels": k})


def _fractional_depth(L, t, spacing):
    """For voxels of tissue t: depth from the inner side / local thickness, and the thickness."""
    inner = (L >= 1) & (L < t)
    outer = (L > t) | (L == 0)
    d_in, d_out = _edt(inner, spacing), _edt(outer, spacing)
    thick = d_in + d_out
    return d_in / np.where(thick > 0, thick, 1.0), thick


def scale_thickness(labels: LabelMap, tissue, factor: float) -> tuple[LabelMap, dict]:
    """Scale a shell's local thickness by `factor`, keeping its inner interface fixed.

    The local thickness at a shell voxel is the sum of its distances to the inner and outer
    tissues. factor < 1: shell voxels deeper than factor x thickness become the outer tissue;
    factor > 1: outer-tissue voxels within (factor - 1) x (thickness at the nearest shell
    voxel) of the shell join it. For CSF, factor 0 removes it: brain fills the space (as a
    three-layer model without CSF does), ventricles included.
    """
    L = _check(labels)
    t = int(Tissue.parse(tissue))
    if t not in (2, 3, 4):
        raise ValueError(f"`tissue` must be a shell (csf, skull, scalp), got {tissue!r}.")
    if not np.isfinite(factor) or factor < 0:
        raise ValueError(f"thickness `factor` must be >= 0, got {factor}; 1 leaves it unchanged.")
    spacing = voxel_sizes(labels.affine)
    new = L.copy()
    depth, thick = _fractional_depth(L, t, spacing)
    shell = L == t
    if factor == 0:
        new[shell] = t - 1 if t == 2 else t + 1 if t < 4 else 0
    elif factor < 1:
        # thinning from the outside: the outer tissue (background for scalp) takes the band,
        # except CSF, which is thinned from the brain's side (the brain takes it)
        if t == 2:
            new[shell & (depth < 1 - factor)] = 1
        else:
            new[shell & (depth > factor)] = t + 1 if t < 4 else 0
    elif factor > 1:
        d, idx = ndimage.distance_transform_edt(~shell, sampling=spacing, return_indices=True)
        nearest_thick = thick[tuple(idx)]
        grow = (~shell) & (L > t) & (d <= (factor - 1) * nearest_thick)
        if t == 4:
            grow = (~shell) & (L == 0) & (d <= (factor - 1) * nearest_thick)
        new[grow] = t
    return _out(labels, new, L, {"kind": f"{Tissue(t).name.lower()}_scale", "factor": float(factor)})


def skull_hole(labels: LabelMap, radius_mm: float, *, seed: int = 0) -> tuple[LabelMap, dict]:
    """Open a cylindrical hole of `radius_mm` through the skull, at a random place on its upper half.

    The axis runs from the skull's centroid through a skull voxel drawn (seeded) from those above
    the centroid; skull voxels within radius_mm of the ray become scalp (soft tissue fills the
    hole, as in Lanfer et al. 2012's hole models).
    """
    L = _check(labels)
    if not np.isfinite(radius_mm) or radius_mm <= 0:
        raise ValueError(f"hole `radius_mm` must be > 0, got {radius_mm}.")
    A = labels.affine
    ijk = np.argwhere(L == 3)
    if ijk.size == 0:
        raise ValueError("the label map has no skull to open a hole in.")
    xyz = ijk @ A[:3, :3].T + A[:3, 3]
    c = xyz.mean(0)
    up = np.flatnonzero(xyz[:, 2] > c[2])
    rng = np.random.default_rng(seed)
    p = xyz[rng.choice(up if up.size else np.arange(len(xyz)))]
    axis = (p - c) / np.linalg.norm(p - c)
    rel = xyz - c
    along = rel @ axis
    dist = np.linalg.norm(rel - along[:, None] * axis, axis=1)
    hit = (along > 0) & (dist <= radius_mm)
    new = L.copy()
    new[tuple(ijk[hit].T)] = 4
    return _out(labels, new, L, {"kind": "skull_hole", "radius_mm": float(radius_mm),
                                 "seed": int(seed), "centre_mm": p.round(2).tolist()})


def skull_close(labels: LabelMap, radius_mm: float) -> tuple[LabelMap, dict]:
    """Close openings in the skull: scalp voxels in the skull solid's closing by a ball become skull."""
    L = _check(labels)
    if not np.isfinite(radius_mm) or radius_mm <= 0:
        raise ValueError(f"closing `radius_mm` must be > 0, got {radius_mm}.")
    spacing = voxel_sizes(labels.affine)
    r = np.ceil(radius_mm / spacing).astype(int)
    g = np.stack(np.meshgrid(*[np.arange(-k, k + 1) * s for k, s in zip(r, spacing)],
                             indexing="ij"))
    ball = np.sum(g * g, axis=0) <= radius_mm**2
    solid = (L >= 1) & (L <= 3)
    pad = int(r.max())
    closed = ndimage.binary_closing(np.pad(solid, pad), ball)[pad:-pad, pad:-pad, pad:-pad]
    new = L.copy()
    new[closed & (L == 4)] = 3
    return _out(labels, new, L, {"kind": "skull_close", "radius_mm": float(radius_mm)})


def perturb_labels(labels: LabelMap, kind: str, *, tissue=None, amplitude: float,
                   seed: int = 0) -> tuple[LabelMap, dict]:
    """Apply one label-map perturbation by name (see `LABEL_KINDS`).

    Arguments:
        labels: the reference LabelMap (nested tissues).
        kind: one of LABEL_KINDS.
        tissue: the tissue (dilate/erode); ignored by the skull- and CSF-specific kinds.
        amplitude: the kind's amplitude (LABEL_KINDS says its unit).
        seed: random seed (skull_hole's position).

    Returns:
        (perturbed LabelMap, description dict with the kind, parameters, seed, voxels changed).
    """
    if kind not in LABEL_KINDS:
        raise ValueError(f"unknown label perturbation {kind!r}; use one of {sorted(LABEL_KINDS)}.")
    if kind == "none":
        out = _out(labels, _check(labels), _check(labels), {"kind": "none"})
    elif kind == "dilate":
        out = dilate_erode(labels, tissue, int(amplitude))
    elif kind == "erode":
        out = dilate_erode(labels, tissue, -int(amplitude))
    elif kind == "skull_scale":
        out = scale_thickness(labels, "skull", amplitude)
    elif kind == "csf_scale":
        out = scale_thickness(labels, "csf", amplitude)
    elif kind == "skull_hole":
        out = skull_hole(labels, amplitude, seed=seed)
    else:
        out = skull_close(labels, amplitude)
    out[1]["seed"] = int(seed)
    return out


def jitter_electrodes(mesh: TetMesh, electrodes: Electrodes, sd_mm: float, *, seed: int = 0,
                      radius_mm=None) -> tuple[Electrodes, dict]:
    """Electrodes re-placed after an isotropic random tangential shift of each centre.

    Each centre moves by a Gaussian vector (sd `sd_mm` per tangential direction) in the scalp's
    tangent plane (the plane normal to the centre's direction from the electrodes' centroid),
    then is projected back onto the scalp by `place_electrodes`.

    Arguments:
        mesh: the TetMesh the electrodes are placed on; electrodes: the reference electrodes.
        sd_mm: position error sd in mm per tangential direction (>= 0).
        seed: random seed; radius_mm: electrode radius (default: from the reference areas).
    """
    if not np.isfinite(sd_mm) or sd_mm < 0:
        raise ValueError(f"electrode position error `sd_mm` must be >= 0, got {sd_mm}.")
    c = electrodes.centres
    n = c - c.mean(0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    g = rng.standard_normal(c.shape) * sd_mm
    g -= np.einsum("ij,ij->i", g, n)[:, None] * n  # tangential part
    if radius_mm is None:
        radius_mm = np.sqrt(electrodes.area_mm2() / np.pi)
    new = place_electrodes(mesh, c + g, radius_mm=radius_mm,
                           contact_impedance_ohm_m2=electrodes.contact_impedance_ohm_m2, names=electrodes.names)
    shift = np.linalg.norm(new.centres - c, axis=1)
    return new, {"kind": "electrode_position", "sd_mm": float(sd_mm), "seed": int(seed),
                 "mean_shift_mm": float(shift.mean()), "max_shift_mm": float(shift.max())}
