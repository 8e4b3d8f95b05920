"""Synthetic MRI and CT head phantoms with ground-truth labels.  [host]

A phantom is a smoothly, randomly deformed ellipsoidal cranium (about 150 x 190 x 190 mm, x left->right,
y posterior->anterior, z inferior->superior, world RAS mm) with an optional neck below it. The
cranium is layered by *signed distance to its outer surface* (Euclidean distance transform, in mm,
so every thickness is independent of the voxel size):

- scalp 3-8 mm (skin, subcutaneous fat, and galea/temporal muscle where it is thick),
- skull 4-9 mm with an outer and an inner table of compact bone around a lower-density diploe,
- CSF 1-5 mm (the thinnest places are ~1 mm, thinner than a typical voxel),
- brain: a grey-matter ribbon (3-4 mm) around a white-matter core, folded by grey "sulci" 14-20 mm
  deep along the zero set of a band-limited random field (12-22 mm wavelengths: thresholded
  smooth noise, a labyrinth of sheets), so white matter forms gyral cores; deep grey nuclei; and
  CSF-filled ventricles (two bent lateral ventricles and a thin third ventricle).

Each thickness is a smooth random field (a low-order cosine series per seed) stretched so that every
range is reached somewhere on the head. Different seeds give different subjects (size, shape, pose
within a few degrees, thicknesses, folding, ventricle size, contrast); the same seed gives the same
subject for every modality and voxel size, so ``make_head("mri", seed=s)`` and
``make_head("ct", seed=s)`` are a co-registered MRI/CT pair.

Images are rendered with partial volume (each voxel is the mean of 2x2x2 sub-samples), then:
MRI gets T1-like contrast relative to white matter = 1, a smooth multiplicative bias field (+-15 %)
and Rician noise; CT gets Hounsfield units and Gaussian noise.

The label map (`LabelMap`, `Tissue` values) is the tissue at each voxel centre, made *strictly nested*
on the voxel grid: every BRAIN voxel's 26 neighbours are BRAIN or CSF, CSF's are BRAIN, CSF or SKULL,
SKULL's are CSF, SKULL or SCALP, and SCALP's are SKULL, SCALP or BACKGROUND. Where a layer is thinner
than the voxels (e.g. 1 mm CSF at 3 mm voxels), the inner tissue is eroded into it (as Vonach et al.
2012 erode the brain where CSF is too thin); the number of relabelled voxels is logged at INFO.
Ventricles are CSF *inside* the brain (labelled CSF, surrounded by BRAIN); a mesher may fill them
into the brain. The neck is soft tissue and is labelled SCALP.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal, NamedTuple

import numpy as np
from scipy import ndimage

from .tissue import Tissue
from .volume import LabelMap, Volume, add_scanner_noise, default_affine

__all__ = ["PhantomHead", "Structure", "STRUCTURE_TISSUE", "make_head", "make_population", "structure_map"]

log = logging.getLogger(__name__)

Modality = Literal["mri", "ct"]

#: Background margin (mm) between the head and every face of a derived field of view.
MARGIN_MM = 10.0
#: Sub-samples per axis for partial volume (each voxel averages SUPERSAMPLE**3 points).
SUPERSAMPLE = 2
#: Random fields are cosine series on the cube [-L, L]^3 of the head frame (mm).
_FIELD_HALF_MM = 160.0
#: Largest grid make_head builds (voxels): a 1 mm head with neck is ~1.1e7 voxels and peaks at
#: ~1.1 GB (~100 bytes per voxel), so this is ~6 GB.
_MAX_VOXELS = 6e7
#: Sulci where |fold field| < this (unit-variance field, gradient ~0.4/mm: ~4 mm wide sheets).
_SULCUS_WIDTH = 0.8
#: Default noise: MRI as a fraction of white-matter intensity, CT in HU.
DEFAULT_NOISE = {"mri": 0.03, "ct": 10.0}


class Structure(IntEnum):
    """Anatomical sub-structures of the phantom (finer than `Tissue`)."""

    AIR = 0
    SKIN = 1
    FAT = 2
    MUSCLE = 3  # galea / temporal muscle in the scalp, muscle in the neck
    OUTER_TABLE = 4
    DIPLOE = 5
    INNER_TABLE = 6
    CSF = 7
    GREY = 8
    WHITE = 9
    DEEP_GREY = 10
    VENTRICLE = 11


#: The `Tissue` of each `Structure`, indexable by Structure value.
STRUCTURE_TISSUE: tuple[Tissue, ...] = (
    Tissue.BACKGROUND,
    Tissue.SCALP, Tissue.SCALP, Tissue.SCALP,
    Tissue.SKULL, Tissue.SKULL, Tissue.SKULL,
    Tissue.CSF,
    Tissue.BRAIN, Tissue.BRAIN, Tissue.BRAIN,
    Tissue.CSF,
)

# Thickness ranges (mm) of the layers, from the task brief (issue 2) and typical adult anatomy:
# scalp 3-8 mm, skull 4-9 mm, CSF 1-5 mm.
SCALP_MM = (3.0, 8.0)
SKULL_MM = (4.0, 9.0)
CSF_MM = (1.0, 5.0)


# ----------------------------------------------------------------------------------------------
# Smooth random fields, evaluated separably on grids (three small tensor contractions) or at points
# ----------------------------------------------------------------------------------------------


def _cos_basis(c: np.ndarray, order: int) -> np.ndarray:
    """DCT-II-like basis cos(pi k (c + L) / 2L), k < order, on [-L, L]; shape (order, n)."""
    k = np.arange(order, dtype=np.float64)[:, None]
    return np.cos(np.pi * k * (np.asarray(c, np.float64)[None, :] + _FIELD_HALF_MM) / (2 * _FIELD_HALF_MM))


@dataclass(frozen=True)
class _CosField:
    """A smooth random field: sum of coef[a, b, c] cos_a(x) cos_b(y) cos_c(z) (low order)."""

    coef: np.ndarray  # (K, K, K)

    @classmethod
    def random(cls, rng: np.random.Generator, order: int, decay: float = 1.0) -> _CosField:
        a, b, c = np.meshgrid(*(np.arange(order),) * 3, indexing="ij")
        total = a + b + c
        coef = rng.standard_normal((order,) * 3) / (1.0 + total) ** decay
        coef[(total == 0) | (total >= order)] = 0.0  # no constant term; isotropic degree cut-off
        return cls(coef)

    def grid(self, axes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        k = self.coef.shape[0]
        bx, by, bz = (_cos_basis(c, k) for c in axes)
        return np.einsum("abc,ax,by,cz->xyz", self.coef, bx, by, bz, optimize=True)

    def points(self, p: np.ndarray) -> np.ndarray:
        k = self.coef.shape[0]
        bx, by, bz = (_cos_basis(p[:, i], k) for i in range(3))
        return np.einsum("abc,ai,bi,ci->i", self.coef, bx, by, bz, optimize=True)


@dataclass(frozen=True)
class _ScaledField:
    """lo + (hi - lo) * clip((f - f_lo) / (f_hi - f_lo), 0, 1) for a _CosField f.

    f_lo, f_hi are the 5th and 95th percentiles of f over the cranium's surface, so each range
    is reached (and held over ~5 % of the surface) on every subject.
    """

    field: _CosField
    f_lo: float
    f_hi: float
    lo: float
    hi: float

    def _map(self, f):
        u = np.clip((f - self.f_lo) / (self.f_hi - self.f_lo), 0.0, 1.0)
        return self.lo + (self.hi - self.lo) * u

    def grid(self, axes):
        """float32 on the grid (in place: these are the largest arrays a phantom builds)."""
        f = self.field.grid(axes).astype(np.float32)
        f -= np.float32(self.f_lo)
        f *= np.float32(1.0 / (self.f_hi - self.f_lo))
        np.clip(f, 0.0, 1.0, out=f)
        f *= np.float32(self.hi - self.lo)
        f += np.float32(self.lo)
        return f

    def points(self, p):
        return self._map(self.field.points(p))


@dataclass(frozen=True)
class _Waves:
    """Band-limited random field sum_j sqrt(2/J) cos(k_j . x + phi_j) (unit variance)."""

    k: np.ndarray  # (J, 3) rad/mm
    phase: np.ndarray  # (J,)

    @classmethod
    def random(cls, rng, n: int, wavelength_mm: tuple[float, float]) -> _Waves:
        d = rng.standard_normal((n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        lam = rng.uniform(*wavelength_mm, size=n)
        return cls(d * (2 * np.pi / lam)[:, None], rng.uniform(0, 2 * np.pi, size=n))

    def grid(self, axes) -> np.ndarray:
        # cos(k.x + phi) = Re(e^{i phi} e^{i kx x} e^{i ky y} e^{i kz z}): separable, so the whole
        # grid is one complex matrix product (n_x n_y, J) @ (J, n_z).
        amp = math.sqrt(2.0 / len(self.phase))
        ex = np.exp(1j * (self.k[:, 0:1] * axes[0][None, :] + self.phase[:, None])).astype(np.complex64)
        ey = np.exp(1j * self.k[:, 1:2] * axes[1][None, :]).astype(np.complex64)
        ez = np.exp(1j * self.k[:, 2:3] * axes[2][None, :]).astype(np.complex64)
        xy = (ex[:, :, None] * ey[:, None, :]).reshape(len(self.phase), -1)
        out = (xy.T @ ez).real.reshape(len(axes[0]), len(axes[1]), len(axes[2]))
        return (amp * out).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# One subject: every random draw, in a fixed order, independent of grid and modality
# ----------------------------------------------------------------------------------------------


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mz @ my @ mx


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@dataclass(frozen=True)
class _Ellipsoid:
    """Ellipsoid in the local head frame, optionally bent (centre z drops by bend * y^2)."""

    centre: tuple[float, float, float]
    semi: tuple[float, float, float]
    bend: float = 0.0

    def level(self, xl, yl, zl):
        """Approximate signed distance (mm, > 0 inside): (1 - r) * smallest semi-axis."""
        cx, cy, cz = self.centre
        ax, ay, az = self.semi
        dy = yl - cy
        r = np.sqrt(((xl - cx) / ax) ** 2 + (dy / ay) ** 2 + ((zl - cz + self.bend * dy * dy) / az) ** 2)
        return (1.0 - r) * min(self.semi)


@dataclass(frozen=True)
class _Subject:
    axes: tuple[float, float, float, float]  # cranium semi-axes (mm): x, y, z above, z below centre
    egg: float  # the cranium narrows anteriorly: x semi-axis * (1 - egg * y / a_y)
    rot: np.ndarray  # (3, 3) local head frame -> head frame H (world orientation)
    shape_field: _CosField  # radial deformation (fraction of radius)
    shape_amp: float
    neck: tuple[float, float, float, float, float, float]  # rx, ry, y centre, z top, z bottom, cap
    scalp: _ScaledField
    skull: _ScaledField
    csf: _ScaledField
    skin_mm: float
    fat: _ScaledField
    outer_table: _ScaledField
    inner_table: _ScaledField
    grey_mm: float  # grey ribbon thickness away from sulci
    fold_mm: float  # depth of the sulci below the ribbon
    folds: _Waves
    ventricles: tuple[_Ellipsoid, ...]
    nuclei: tuple[_Ellipsoid, ...]
    bone_density: _ScaledField  # 0..1: modulates CT table HU and the diploe in CT and MRI
    bias: _CosField
    bias_scale: float  # bias = exp(bias_scale * field)
    seed: int
    contrast_seed: np.random.SeedSequence  # per-subject intensity draws
    noise_seed: np.random.SeedSequence
    bbox: np.ndarray  # (2, 3) head-frame bounding box (mm) with neck
    bbox_no_neck: np.ndarray  # (2, 3) without neck

    def cranium_r(self, xl, yl, zl):
        """Normalised radius |q| (float32) of local points, q = local / semi-axes (egg-shaped)."""
        ax, ay, az_up, az_lo = (np.float32(a) for a in self.axes)
        ax_eff = ax * (np.float32(1.0) - np.float32(self.egg) * np.clip(yl / ay, -1.0, 1.0))
        r = (xl / ax_eff) ** 2
        r += (yl / ay) ** 2
        r += (zl / np.where(zl > 0, az_up, az_lo)) ** 2
        return np.sqrt(r, out=r)

    def neck_level(self, xl, yl, zl):
        """Approximate signed distance to the neck (mm, > 0 inside)."""
        rx, ry, yc, ztop, zbot, cap = self.neck
        below = np.minimum(zl - zbot, 0.0)
        r = np.sqrt((xl / rx) ** 2 + ((yl - yc) / ry) ** 2 + (below / cap) ** 2)
        return np.minimum((1.0 - r) * min(rx, ry, cap), ztop - zl)


def _cranium_surface(sub_partial: dict, dirs: np.ndarray) -> np.ndarray:
    """Points (n, 3) on the cranium surface in the head frame, one per local direction (bisection)."""
    rot, field, amp = sub_partial["rot"], sub_partial["shape_field"], sub_partial["shape_amp"]
    ax, ay, az_up, az_lo = sub_partial["axes"]
    egg = sub_partial["egg"]
    lo = np.full(len(dirs), 20.0)
    hi = np.full(len(dirs), 250.0)
    for _ in range(50):  # bisection to ~2e-13 of 230 mm
        lam = 0.5 * (lo + hi)
        pl = dirs * lam[:, None]
        ax_eff = ax * (1.0 - egg * np.clip(pl[:, 1] / ay, -1.0, 1.0))
        az = np.where(pl[:, 2] > 0, az_up, az_lo)
        r = np.sqrt((pl[:, 0] / ax_eff) ** 2 + (pl[:, 1] / ay) ** 2 + (pl[:, 2] / az) ** 2)
        f = r - 1.0 - amp * field.points(pl @ rot.T)
        inside = f < 0
        lo = np.where(inside, lam, lo)
        hi = np.where(inside, hi, lam)
    return (dirs * (0.5 * (lo + hi))[:, None]) @ rot.T


def _scaled(rng, order, surface, lo, hi) -> _ScaledField:
    f = _CosField.random(rng, order)
    v = f.points(surface)
    return _ScaledField(f, float(np.percentile(v, 5)), float(np.percentile(v, 95)), lo, hi)


def _make_subject(seed: int) -> _Subject:
    ss = np.random.SeedSequence(seed)
    geo_ss, contrast_ss, noise_ss = ss.spawn(3)
    rng = np.random.default_rng(geo_ss)
    # Adult head ~150 x 190 x 190 mm (breadth, length, vertex-to-skull-base), +-5 % per axis.
    scale = 1.0 + 0.05 * np.clip(rng.standard_normal(4), -2, 2)
    axes = (75.0 * scale[0], 95.0 * scale[1], 100.0 * scale[2], 90.0 * scale[3])
    egg = rng.uniform(0.03, 0.08)
    # Pose within a few degrees (pitch up to 6, roll and yaw up to 3).
    rot = _rotation(np.deg2rad(rng.uniform(-6, 6)), np.deg2rad(rng.uniform(-3, 3)),
                    np.deg2rad(rng.uniform(-3, 3)))
    shape_field = _CosField.random(rng, 4)
    dirs = _fibonacci_sphere(4000)
    probe = shape_field.points(dirs * 90.0)
    shape_amp = rng.uniform(0.03, 0.05) / probe.std()  # radial deformation of 3-5 % (rms)
    partial = dict(rot=rot, shape_field=shape_field, shape_amp=shape_amp, axes=axes, egg=egg)
    surface = _cranium_surface(partial, dirs)

    scalp = _scaled(rng, 6, surface, *SCALP_MM)
    skull = _scaled(rng, 6, surface, *SKULL_MM)
    csf = _scaled(rng, 6, surface, *CSF_MM)
    skin_mm = rng.uniform(1.0, 1.5)
    fat = _scaled(rng, 6, surface, 1.5, 5.0)
    outer_table = _scaled(rng, 5, surface, 1.2, 2.4)
    inner_table = _scaled(rng, 5, surface, 0.8, 1.6)
    grey_mm = rng.uniform(3.0, 4.0)
    fold_mm = rng.uniform(14.0, 20.0)
    folds = _Waves.random(rng, 40, (12.0, 22.0))

    # Neck: elliptic cylinder below the cranium, slightly posterior, with a rounded lower end.
    neck = (rng.uniform(48, 56), rng.uniform(52, 60), rng.uniform(-20, -10), -40.0,
            -axes[3] - rng.uniform(30, 50), rng.uniform(20, 30))

    # Ventricles: bent lateral ventricles either side of a 3 mm septum, a thin third ventricle.
    vs = rng.uniform(0.7, 1.4)  # ventricle size varies a lot between adults
    vx, vy, vz = 3.0 + 2.0 * vs, 32.0 * rng.uniform(0.9, 1.1), 8.0 + 3.0 * vs
    z0 = rng.uniform(5, 15)
    bend = 12.0 / vy**2
    yc = rng.uniform(-8, 0)
    ventricles = (
        _Ellipsoid((-(vx + 1.5), yc, z0), (vx, vy, vz), bend),
        _Ellipsoid((vx + 1.5, yc, z0), (vx, vy, vz), bend),
        _Ellipsoid((0.0, yc - 6, z0 - vz - 9), (1.5, 12.0, 8.0)),
    )
    nuclei = (  # thalami and lentiform nuclei
        _Ellipsoid((-(vx + 9), yc - 12, z0 - 18), (8.0, 14.0, 9.0)),
        _Ellipsoid((vx + 9, yc - 12, z0 - 18), (8.0, 14.0, 9.0)),
        _Ellipsoid((-(vx + 20), yc + 10, z0 - 12), (6.0, 16.0, 10.0)),
        _Ellipsoid((vx + 20, yc + 10, z0 - 12), (6.0, 16.0, 10.0)),
    )
    bone_density = _scaled(rng, 5, surface, 0.0, 1.0)
    bias = _CosField.random(rng, 3)
    # Bias field exp(+-0.14) = +-15 % at the extremes of the field over the head's volume.
    probe_pts = np.concatenate([surface * f for f in (0.3, 0.6, 0.8, 1.0)])
    bias_scale = np.log(1.15) / np.abs(bias.points(probe_pts)).max()

    # Bounding box in the head frame (surface samples ~5 mm apart: the extreme is missed by
    # < 0.1 mm; 1 mm of slack covers it).
    rx, ry, ycn, ztop, zbot, cap = neck
    th = np.linspace(0, 2 * np.pi, 128, endpoint=False)
    ring = np.stack([rx * np.cos(th), ycn + ry * np.sin(th)], axis=1)
    neck_pts = [np.column_stack([ring, np.full(len(th), z)]) for z in np.linspace(zbot, ztop, 12)]
    for a in np.linspace(0, np.pi / 2, 12):  # rounded end
        neck_pts.append(np.column_stack([rx * np.cos(th) * np.cos(a), ycn + ry * np.sin(th) * np.cos(a),
                                         np.full(len(th), zbot - cap * np.sin(a))]))
    neck_pts = np.concatenate(neck_pts) @ rot.T
    bbox_no_neck = np.stack([surface.min(0) - 1.0, surface.max(0) + 1.0])
    allp = np.concatenate([surface, neck_pts])
    bbox = np.stack([allp.min(0) - 1.0, allp.max(0) + 1.0])

    return _Subject(axes=axes, egg=egg, rot=rot, shape_field=shape_field, shape_amp=shape_amp,
                    neck=neck, scalp=scalp, skull=skull, csf=csf, skin_mm=skin_mm, fat=fat,
                    outer_table=outer_table, inner_table=inner_table, grey_mm=grey_mm,
                    fold_mm=fold_mm, folds=folds, ventricles=ventricles, nuclei=nuclei,
                    bone_density=bone_density, bias=bias, bias_scale=bias_scale,
                    seed=seed, contrast_seed=contrast_ss, noise_seed=noise_ss,
                    bbox=bbox, bbox_no_neck=bbox_no_neck)


# ----------------------------------------------------------------------------------------------
# Argument checks and the grid
# ----------------------------------------------------------------------------------------------


def _check_modality(modality) -> str:
    m = str(modality).lower() if isinstance(modality, str) else None
    if m not in ("mri", "ct"):
        raise ValueError(f"`modality` must be 'mri' or 'ct', got {modality!r}.")
    return m


def _check_voxel(voxel_mm) -> np.ndarray:
    try:
        vox = np.broadcast_to(np.asarray(voxel_mm, dtype=np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise ValueError(
            f"`voxel_mm` must be a positive number or three of them (mm), got {voxel_mm!r}.") from None
    if not np.all(np.isfinite(vox)) or np.any(vox <= 0):
        raise ValueError(f"`voxel_mm` must be positive and finite (mm), got {voxel_mm!r}.")
    if np.any(vox > 6.0):
        raise ValueError(
            f"`voxel_mm`={voxel_mm!r} is too coarse: the 3-9 mm scalp and skull layers cannot be "
            "represented; use voxels of at most 6 mm.")
    return vox


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"`seed` must be a non-negative integer, got {seed!r}.")
    return int(seed)


def _grid_shape(sub: _Subject, vox: np.ndarray, shape, neck: bool) -> tuple[tuple[int, int, int], np.ndarray]:
    """The grid shape and the head-frame offset of the world origin (world = H - centre)."""
    bbox = sub.bbox if neck else sub.bbox_no_neck
    extent = bbox[1] - bbox[0]
    centre = bbox.mean(axis=0)
    if shape is None:
        shp = np.ceil((extent + 2 * MARGIN_MM) / vox).astype(int) + 1
        shape = tuple(int(n) for n in shp)
    else:
        try:
            ok = len(shape) == 3 and all(
                isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in shape)
        except TypeError:
            ok = False
        if not ok:
            raise ValueError(f"`shape` must be None or three positive integers, got {shape!r}.")
        shape = tuple(int(n) for n in shape)
        # The head must stay one voxel (plus 1 mm) clear of every face, so the border voxels and
        # their partial-volume sub-samples are pure background.
        need = np.ceil((extent + 2 * (vox + 1.0)) / vox).astype(int) + 1
        if any(n < m for n, m in zip(shape, need)):
            raise ValueError(
                f"`shape`={shape} is too small for this head (seed and voxel_mm={vox.tolist()} mm, "
                f"extent {np.round(extent, 1).tolist()} mm): it needs at least {tuple(need.tolist())} "
                "voxels; pass shape=None to derive a grid with a "
                f"{MARGIN_MM:g} mm background margin.")
    if float(np.prod(shape)) > _MAX_VOXELS:
        raise ValueError(
            f"the phantom grid would have {np.prod(shape):.3g} voxels (shape {shape}); "
            f"that is more than {_MAX_VOXELS:.2g} (~100 bytes each while building); use a larger "
            "`voxel_mm` or a smaller `shape`.")
    return shape, centre


# ----------------------------------------------------------------------------------------------
# Geometry on the voxel grid
# ----------------------------------------------------------------------------------------------


@dataclass
class _Geometry:
    """Fields at voxel centres that decide the structure at any point by thresholds.

    "Sharp" fields (interpolated to partial-volume sub-samples) and smooth per-voxel thresholds
    (taken from the sub-sample's own voxel; they vary by < 0.3 mm per mm, so within a voxel the
    error is far below the sub-sample spacing). All float32, shape (x, y, z) or gathered (n,).
    """

    d_cran: np.ndarray  # signed distance to the cranium's outer surface, mm, > 0 inside
    d_head: np.ndarray  # signed distance to the head (cranium u neck), mm, > 0 inside
    wm: np.ndarray  # > 0 in white matter (mm)
    vent: np.ndarray  # > 0 in ventricles
    nuc: np.ndarray  # > 0 in deep grey nuclei
    t1: np.ndarray  # depth of the scalp/skull boundary below the cranium surface, mm
    t1o: np.ndarray  # depth of the outer table / diploe boundary
    t2i: np.ndarray  # depth of the diploe / inner table boundary
    t2: np.ndarray  # depth of the skull/CSF boundary
    t3: np.ndarray  # depth of the CSF/brain boundary
    skinfat: np.ndarray  # depth of the fat / muscle boundary below the head surface
    density: np.ndarray  # bone density 0..1
    skin: float

    SHARP = ("d_cran", "d_head", "wm", "vent", "nuc")
    SMOOTH = ("t1", "t1o", "t2i", "t2", "t3", "skinfat", "density")

    def take(self, flat_idx: np.ndarray) -> _Geometry:
        """The same fields at flat voxel indices (n,)."""
        return _Geometry(**{k: getattr(self, k).ravel()[flat_idx] for k in self.SHARP + self.SMOOTH},
                         skin=self.skin)


def _signed_distance(F: np.ndarray, vox: np.ndarray, scale_mm: float, iterations: int = 3) -> np.ndarray:
    """Signed distance (mm, > 0 inside) to the surface {F = 0} of an implicit function F (< 0 inside).

    Near the surface (|F| < 3 voxels / scale_mm, the "band") the distance is first order,
    s1 = -F / |grad F| with grad F by central differences (error O(h^2 / radius)); each band voxel
    x also gives a surface point (foot) x + s1 n and the outward unit normal n there. Deeper
    inside, the Euclidean distance transform (scipy.ndimage.distance_transform_edt, mm) gives the
    nearest outside voxel q; from it, a few fixed-point steps move to the band voxel v nearest to
    p + d n(v) (the foot of p's normal), and d(p) = (foot(v) - p) . n(v), the distance to the
    surface's tangent plane at a surface point within about a voxel of p's true nearest point.
    Far outside only the sign of the result is meaningful.

    Arguments:
        F: (x, y, z) implicit function, < 0 inside, with |grad F| ~ 1 / scale_mm near the surface.
        vox: (3,) voxel sizes in mm.
        scale_mm: smallest length over which F changes by 1 (e.g. the smallest semi-axis).
        iterations: fixed-point steps towards each deep voxel's foot point.

    Returns:
        (x, y, z) float32 signed distance in mm.
    """
    vox = np.asarray(vox, np.float64)
    shape = np.array(F.shape)
    d = (-F * scale_mm).astype(np.float32)  # far from the surface: the sign only
    band_width = 3.0 * vox.max() / scale_mm
    band = np.abs(F) < band_width
    band[[0, -1]] = band[:, [0, -1]] = band[:, :, [0, -1]] = False  # central differences need both sides
    bidx = np.flatnonzero(band)
    del band
    Ff = F.ravel()
    strides = np.array(F.strides) // F.itemsize
    grad = np.stack([(Ff[bidx + strides[a]].astype(np.float64) - Ff[bidx - strides[a]]) / (2 * vox[a])
                     for a in range(3)])
    gnorm = np.maximum(np.sqrt((grad**2).sum(0)), 1e-12)
    s1 = -Ff[bidx] / gnorm
    d.ravel()[bidx] = s1
    inside = F < 0
    if not inside.any() or len(bidx) == 0:
        return d
    normal = grad / gnorm  # (3, n_band) outward
    foot = np.stack(np.unravel_index(bidx, F.shape)) * vox[:, None] + s1 * normal  # mm
    del grad, gnorm
    slot = np.full(F.size, -1, np.int32)  # flat voxel index -> band slot
    slot[bidx] = np.arange(len(bidx), dtype=np.int32)

    # EDT over the inside's bounding box (+2 voxels); outside the box nothing is inside.
    nz = [np.flatnonzero(inside.any(axis=tuple(b for b in range(3) if b != a))) for a in range(3)]
    lo = np.array([max(int(n[0]) - 2, 0) for n in nz])
    box = tuple(slice(int(l), min(int(n[-1]) + 3, s)) for l, n, s in zip(lo, nz, F.shape))
    ins = inside[box]
    del inside
    _, ind = ndimage.distance_transform_edt(ins, sampling=vox, return_indices=True)
    p = np.nonzero(ins & (np.abs(F[box]) >= band_width))  # deep inside voxels (box indices)
    del ins
    q = np.ravel_multi_index(tuple(ind[a][p] + lo[a] for a in range(3)), F.shape)
    del ind
    pmm = np.stack(p).astype(np.float64) + lo[:, None]  # voxel index of p in the full grid
    pmm *= vox[:, None]
    k = slot[q]
    if np.any(k < 0):  # the nearest outside voxel of a deep voxel is always next to the surface
        raise AssertionError("distance transform feature outside the surface band")
    dist = ((foot[:, k] - pmm) * normal[:, k]).sum(0)
    for _ in range(iterations):
        land = pmm + dist * normal[:, k]
        v = np.rint(land / vox[:, None]).astype(np.int64)
        np.clip(v, 0, shape[:, None] - 1, out=v)
        k_new = slot[np.ravel_multi_index(tuple(v), F.shape)]
        k = np.where(k_new >= 0, k_new, k)
        dist = ((foot[:, k] - pmm) * normal[:, k]).sum(0)
    db = d[box]
    db[p] = dist
    return d


def _geometry(sub: _Subject, shape, vox: np.ndarray, centre: np.ndarray, neck: bool) -> _Geometry:
    affine = default_affine(vox, shape)
    # Head-frame coordinates of the voxel centres along each axis (world is axis-aligned with H).
    ax_h = tuple(affine[i, i] * np.arange(shape[i]) + affine[i, 3] + centre[i] for i in range(3))
    hx, hy, hz = (a.astype(np.float32) for a in ax_h)
    R = sub.rot.astype(np.float32)
    # local = H @ R, evaluated by broadcasting the three axes.
    xl, yl, zl = (hx[:, None, None] * R[0, c] + hy[None, :, None] * R[1, c] + hz[None, None, :] * R[2, c]
                  for c in range(3))

    def smooth(field):
        return field.grid(ax_h).astype(np.float32)

    # Cranium: F = r - 1 - delta (< 0 inside), |grad F| ~ 1 / radius.
    F = sub.cranium_r(xl, yl, zl)
    F -= 1.0
    F -= sub.shape_amp * smooth(sub.shape_field)
    d_cran = _signed_distance(F, vox, scale_mm=min(sub.axes))
    del F

    # Head = cranium u neck; the neck level is already a distance to first order (its error is
    # < 10 % of the depth, which only moves the neck's fat/muscle boundary by < 0.5 mm).
    d_head = np.maximum(d_cran, sub.neck_level(xl, yl, zl).astype(np.float32)) if neck else d_cran

    # Layer depths (mm below the cranium surface).
    t1 = smooth(sub.scalp)
    t2 = t1 + smooth(sub.skull)
    t3 = t2 + smooth(sub.csf)
    skull_t = t2 - t1
    # Tables leave at least 30 % of the skull to the diploe.
    t1o = t1 + np.minimum(smooth(sub.outer_table), 0.4 * skull_t)
    t2i = t2 - np.minimum(smooth(sub.inner_table), 0.3 * skull_t)
    del skull_t

    # White matter: deeper than the grey ribbon. Sulci: near the zero set of the fold field (a
    # labyrinth of sheets, as the zero set of any smooth random field), the ribbon deepens in a V
    # of depth fold_mm and ~4 mm width at the surface, so white matter forms gyral cores.
    sulcus = sub.folds.grid(ax_h)
    np.abs(sulcus, out=sulcus)
    sulcus *= -1.0 / _SULCUS_WIDTH
    sulcus += 1.0
    np.maximum(sulcus, 0.0, out=sulcus)
    wm = d_cran - t3
    wm -= sub.grey_mm + sub.fold_mm * sulcus
    del sulcus

    # Ventricles and nuclei: evaluated only in a box around them (local |x|<60, |y|<80, |z|<60).
    vent = np.full(shape, -100.0, np.float32)
    nuc = np.full(shape, -100.0, np.float32)
    corners = np.array([[sx * 60, sy * 80, sz * 60] for sx in (-1, 1) for sy in (-1, 1)
                        for sz in (-1, 1)]) @ sub.rot.T
    cb = tuple(slice(int(np.searchsorted(ax_h[a], corners[:, a].min())),
                     int(np.searchsorted(ax_h[a], corners[:, a].max()))) for a in range(3))
    xs, ys, zs = xl[cb], yl[cb], zl[cb]
    vent[cb] = np.max([e.level(xs, ys, zs) for e in sub.ventricles], axis=0)
    nuc[cb] = np.max([e.level(xs, ys, zs) for e in sub.nuclei], axis=0)
    del xl, yl, zl, xs, ys, zs

    return _Geometry(d_cran=d_cran, d_head=d_head, wm=wm, vent=vent, nuc=nuc, t1=t1, t1o=t1o,
                     t2i=t2i, t2=t2, t3=t3, skinfat=sub.skin_mm + smooth(sub.fat),
                     density=smooth(sub.bone_density), skin=float(sub.skin_mm))


def _classify(g: _Geometry, d_cran, d_head, wm, vent, nuc) -> np.ndarray:
    """Structure (uint8) from sharp fields at points and the smooth thresholds of their voxels.

    Every Structure is a conjunction of one-sided tests on the fields (the later assignments
    override), so the set of field values giving one Structure is convex.
    """
    s = np.zeros(d_cran.shape, np.uint8)
    head = d_head > 0
    s[head] = Structure.MUSCLE
    s[head & (d_head < g.skinfat)] = Structure.FAT
    s[head & (d_head < g.skin)] = Structure.SKIN
    s[d_cran > g.t1] = Structure.OUTER_TABLE
    s[d_cran > g.t1o] = Structure.DIPLOE
    s[d_cran > g.t2i] = Structure.INNER_TABLE
    s[d_cran > g.t2] = Structure.CSF
    brain = d_cran > g.t3
    s[brain] = Structure.GREY
    s[brain & (wm > 0)] = Structure.WHITE
    s[brain & (nuc > 0)] = Structure.DEEP_GREY
    s[brain & (vent > 0)] = Structure.VENTRICLE
    return s


# ----------------------------------------------------------------------------------------------
# Intensities
# ----------------------------------------------------------------------------------------------


def _intensity_table(modality: str, rng: np.random.Generator) -> tuple[np.ndarray, tuple, tuple]:
    """Constant intensity per Structure, plus (lo, hi) ranges for density-modulated bone.

    Returns (table (12,), compact bone range, diploe range); bone intensities are
    lo + (hi - lo) * density.
    """
    t = np.zeros(len(Structure))
    if modality == "mri":
        # T1-weighted, relative to white matter = 1 (typical 3D T1 ratios, e.g. MPRAGE/SPGR):
        # fat brightest, WM > deep GM > GM > muscle > CSF, compact bone and air dark.
        t[Structure.AIR] = 0.0
        t[Structure.SKIN] = rng.uniform(0.45, 0.6)
        t[Structure.FAT] = rng.uniform(0.95, 1.15)
        t[Structure.MUSCLE] = rng.uniform(0.38, 0.48)
        t[Structure.CSF] = t[Structure.VENTRICLE] = rng.uniform(0.12, 0.22)
        t[Structure.GREY] = rng.uniform(0.58, 0.66)
        t[Structure.WHITE] = 1.0
        t[Structure.DEEP_GREY] = t[Structure.GREY] + 0.1
        tables = (0.04, 0.1)
        diploe = (0.3, 0.6)  # fatty marrow: brighter than compact bone, varying
    else:
        # Hounsfield units (air -1000, water 0): soft tissue 40-50, fat -90, CSF ~8, grey ~38,
        # white ~30 (poor CSF/brain contrast as in real CT), cortical bone 1200-1800, diploe ~700.
        t[Structure.AIR] = -1000.0
        t[Structure.SKIN] = rng.uniform(35, 45)
        t[Structure.FAT] = rng.uniform(-100, -80)
        t[Structure.MUSCLE] = rng.uniform(40, 55)
        t[Structure.CSF] = t[Structure.VENTRICLE] = rng.uniform(5, 11)
        t[Structure.GREY] = rng.uniform(36, 40)
        t[Structure.WHITE] = rng.uniform(28, 32)
        t[Structure.DEEP_GREY] = t[Structure.GREY]
        tables = (1200.0, 1800.0)
        diploe = (550.0, 850.0)
    return t, tables, diploe


def _intensity(s: np.ndarray, density: np.ndarray, table, tables, diploe, modality) -> np.ndarray:
    val = table.astype(np.float32)[s]
    bone = tables[0] + (tables[1] - tables[0]) * density
    val = np.where(s == Structure.OUTER_TABLE, bone, val)
    # CT: the inner table is slightly less dense than the outer one.
    inner = bone - 0.1 * (tables[1] - tables[0]) if modality == "ct" else bone
    val = np.where(s == Structure.INNER_TABLE, inner, val)
    return np.where(s == Structure.DIPLOE, diploe[0] + (diploe[1] - diploe[0]) * density, val)


def _render(g: _Geometry, s_centre: np.ndarray, modality: str,
            rng_contrast: np.random.Generator, mixed_only: bool = True) -> np.ndarray:
    """Partial-volume image: each voxel is the mean intensity of SUPERSAMPLE^3 sub-samples.

    Sub-samples sit at offsets (2m + 1 - S) / (2S) voxels (m < S) along each axis; the sharp fields
    are trilinearly interpolated there from the 8 surrounding voxel centres. A voxel whose 3x3x3
    neighbourhood has one Structure is pure: every sub-sample's fields are convex combinations of
    values that pass the same (convex) set of tests, so only mixed voxels are sub-sampled
    (`mixed_only=False` sub-samples every interior voxel; the tests compare the two).
    """
    table, tables, diploe = _intensity_table(modality, rng_contrast)
    image = _intensity(s_centre, g.density, table, tables, diploe, modality).astype(np.float64)
    mixed = ndimage.maximum_filter(s_centre, size=3) != ndimage.minimum_filter(s_centre, size=3)
    if not mixed_only:
        mixed[1:-1, 1:-1, 1:-1] = True
    idx = np.flatnonzero(mixed)
    del mixed
    if len(idx) == 0:
        return image
    shape = s_centre.shape
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    # Mixed voxels are never on the border (the border and its neighbours are pure air).
    ijk = np.stack(np.unravel_index(idx, shape))
    assert np.all(ijk > 0) and np.all(ijk < np.array(shape)[:, None] - 1)
    del ijk
    S = SUPERSAMPLE
    # Linear interpolation weights of each sub-sample offset on the neighbours -1, 0, +1 (S, 3).
    W = np.zeros((S, 3), np.float32)
    for m in range(S):
        o = (2 * m + 1 - S) / (2 * S)
        W[m, 1] = 1.0 - abs(o)
        W[m, 0 if o < 0 else 2] += abs(o)
    nbr = np.array([dx * strides[0] + dy * strides[1] + dz * strides[2]
                    for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)])
    sharp = [getattr(g, k).ravel() for k in _Geometry.SHARP]
    values = np.empty(len(idx), np.float64)
    chunk = 1 << 17
    for c0 in range(0, len(idx), chunk):
        ci = idx[c0:c0 + chunk]
        gi = g.take(ci)
        sub = []
        for f in sharp:
            nb = f[ci[None, :] + nbr[:, None]].reshape(3, 3, 3, -1)
            # Trilinear interpolation at all S^3 sub-samples: three small contractions.
            v = np.einsum("ai,bj,ck,ijkn->abcn", W, W, W, nb, optimize=True)
            sub.append(v.reshape(S**3, -1))
        acc = np.zeros(len(ci), np.float64)
        for m in range(S**3):
            s = _classify(gi, *(v[m] for v in sub))
            acc += _intensity(s, gi.density, table, tables, diploe, modality)
        values[c0:c0 + chunk] = acc / S**3
    image.ravel()[idx] = values
    return image


def _nested_labels(s: np.ndarray) -> tuple[np.ndarray, int]:
    """Tissue labels from voxel-centre structures, strictly nested with 26-neighbourhoods."""
    tissue = np.asarray(STRUCTURE_TISSUE, dtype=np.uint8)[s]
    ventricle = s == Structure.VENTRICLE
    m4 = tissue != Tissue.BACKGROUND
    m3 = (tissue == Tissue.SKULL) | (tissue == Tissue.CSF) | (tissue == Tissue.BRAIN)
    m2 = (tissue == Tissue.CSF) | (tissue == Tissue.BRAIN)
    m1 = (tissue == Tissue.BRAIN) | ventricle
    cube = np.ones((3, 3, 3), bool)
    # Each mask must lie in the 26-erosion of the next outer one (the mask of the nested solid).
    m3 &= ndimage.binary_erosion(m4, cube)
    m2 &= ndimage.binary_erosion(m3, cube)
    m1 &= ndimage.binary_erosion(m2, cube)
    out = np.zeros(s.shape, np.uint8)
    out[m4] = Tissue.SCALP
    out[m3] = Tissue.SKULL
    out[m2] = Tissue.CSF
    out[m1] = Tissue.BRAIN
    out[m1 & ventricle] = Tissue.CSF  # ventricles: CSF inside the brain
    changed = int((out != tissue).sum())
    return out, changed


# ----------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------


class PhantomHead(NamedTuple):
    """A synthetic scan and its ground truth, as `make_head` returns them.

    A named pair: ``volume, labels = make_head(...)`` unpacks it, ``head.labels`` names a field.
    (Not a result with a report: a phantom has nothing to report; the pipeline stages return
    their value, and a ``*_reported`` twin returns (value, report).)

    Attributes:
        volume: `Volume` (x, y, z) float64 intensities (MRI: white matter = 1; CT: HU).
        labels: `LabelMap` (x, y, z) strictly nested `Tissue` values on the same grid and affine.
    """

    volume: Volume
    labels: LabelMap


def _setup(seed, voxel_mm, shape, neck):
    seed = _check_seed(seed)
    vox = _check_voxel(voxel_mm)
    if not isinstance(neck, (bool, np.bool_)):
        raise ValueError(f"`neck` must be True or False, got {neck!r}.")
    sub = _make_subject(seed)
    shape, centre = _grid_shape(sub, vox, shape, bool(neck))
    return sub, vox, shape, centre


def make_head(modality: Modality = "mri", *, shape: tuple[int, int, int] | None = None,
              voxel_mm: float | tuple[float, float, float] = 2.0, noise: float | None = None,
              seed: int = 0, neck: bool = True, bias: bool = True) -> PhantomHead:
    """A synthetic head scan (MRI or CT) and its strictly nested tissue labels.

    Arguments:
        modality: "mri" (T1-like, white matter = 1, Rician noise, bias field) or "ct" (Hounsfield
            units, Gaussian noise).
        shape: grid (x, y, z) in voxels, centred on the head; None derives it from the head's
            bounding box plus a 10 mm background margin. A shape that leaves less than one voxel
            (+1 mm) of background around the head raises ValueError.
        voxel_mm: voxel edge length(s) in mm, scalar or (3,), at most 6.
        noise: MRI: Rician noise sigma as a fraction of white-matter intensity (default 0.03);
            CT: Gaussian noise sigma in HU (default 10). 0 gives the noise-free image.
        seed: subject; the same seed gives the same anatomy for both modalities and any voxel size.
        neck: add a neck (soft tissue, labelled SCALP) below the cranium.
        bias: MRI only: multiply by a smooth random bias field (+-15 %).

    Returns:
        PhantomHead (volume, labels), a named pair: `Volume` (x, y, z) float64 intensities and
        `LabelMap` (x, y, z) `Tissue` values on the same grid and affine (`default_affine(voxel_mm, shape)`: world origin at the
        grid centre, RAS mm). Labels are the voxel-centre tissue made strictly nested (see module
        docstring); ventricles are CSF inside the brain.
    """
    modality = _check_modality(modality)
    if noise is None:
        noise = DEFAULT_NOISE[modality]
    try:
        noise = float(noise)
    except (TypeError, ValueError):
        raise ValueError(f"`noise` must be a number >= 0, got {noise!r}.") from None
    if not math.isfinite(noise) or noise < 0:
        raise ValueError(
            f"`noise` must be finite and >= 0 (MRI: fraction of white matter, CT: HU), got {noise!r}.")
    if not isinstance(bias, (bool, np.bool_)):
        raise ValueError(f"`bias` must be True or False, got {bias!r}.")
    sub, vox, shape, centre = _setup(seed, voxel_mm, shape, neck)
    g = _geometry(sub, shape, vox, centre, bool(neck))
    centre_s = _classify(g, g.d_cran, g.d_head, g.wm, g.vent, g.nuc)
    labels, changed = _nested_labels(centre_s)
    if changed:
        log.info("phantom seed %d: %d voxels relabelled to their enclosing tissue for strict 26-neighbour "
                 "nesting (layers thinner than the %s mm voxels)", sub.seed, changed, vox.tolist())
    image = _render(g, centre_s, modality, np.random.default_rng(sub.contrast_seed))
    del g, centre_s
    noise_rng = np.random.default_rng(sub.noise_seed)
    if modality == "mri":
        if bias:
            affine = default_affine(vox, shape)
            ax_h = tuple(affine[i, i] * np.arange(shape[i]) + affine[i, 3] + centre[i] for i in range(3))
            image *= np.exp(sub.bias_scale * sub.bias.grid(ax_h))
    # MRI: Rician noise with sd relative to white matter (= 1); CT: Gaussian noise in HU.
    image = add_scanner_noise(image, noise, modality, noise_rng)
    affine = default_affine(vox, shape)
    if np.any(labels[[0, -1]]) or np.any(labels[:, [0, -1]]) or np.any(labels[:, :, [0, -1]]):
        raise AssertionError("phantom head touches the grid border")  # guarded by _grid_shape
    return PhantomHead(Volume(image, affine), LabelMap(labels, affine))


def structure_map(*, shape: tuple[int, int, int] | None = None,
                  voxel_mm: float | tuple[float, float, float] = 2.0, seed: int = 0,
                  neck: bool = True) -> np.ndarray:
    """The `Structure` at each voxel centre of the grid `make_head` builds with the same arguments.

    This is the unrepaired fine ground truth (grey/white matter, tables, diploe, ...); map it to
    tissues with ``np.asarray(STRUCTURE_TISSUE)[s]``. It differs from `make_head`'s labels only where
    strict nesting moved a label outward.

    Arguments:
        shape, voxel_mm, seed, neck: as for `make_head`.

    Returns:
        (x, y, z) uint8 `Structure` values.
    """
    sub, vox, shape, centre = _setup(seed, voxel_mm, shape, neck)
    g = _geometry(sub, shape, vox, centre, bool(neck))
    return _classify(g, g.d_cran, g.d_head, g.wm, g.vent, g.nuc)


def make_population(n: int, modality: Modality = "mri", seed: int = 0,
                    **kw) -> list[PhantomHead]:
    """`n` different subjects: subject i is ``make_head(modality, seed=seed + i, **kw)``.

    Arguments:
        n: number of subjects (>= 1).
        modality: "mri" or "ct".
        seed: seed of the first subject; use disjoint ranges for, e.g., atlas and test subjects.
        **kw: shape, voxel_mm, noise, neck, bias as for `make_head`.

    Returns:
        list of n PhantomHead (volume, labels) pairs.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"`n` must be a positive integer (number of subjects), got {n!r}.")
    seed = _check_seed(seed)
    if "seed" in kw:
        raise ValueError("pass the first subject's seed as `seed`, not inside **kw.")
    return [make_head(modality, seed=seed + i, **kw) for i in range(int(n))]
