"""Image volumes and label maps on a voxel grid with a world (RAS, mm) affine.  [host]"""

import equinox as eqx
import numpy as np

from .tissue import Tissue


def check_affine(affine: np.ndarray, owner: str) -> None:
    if affine.shape != (4, 4):
        raise ValueError(f"`{owner}.affine` must be 4x4, got shape {affine.shape}.")
    if not np.all(np.isfinite(affine)):
        raise ValueError(f"`{owner}.affine` contains NaN or Inf; pass a finite voxel-to-mm affine.")
    if not np.allclose(affine[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(
            f"`{owner}.affine` last row is {affine[3].tolist()}, expected [0, 0, 0, 1]."
        )
    det = np.linalg.det(affine[:3, :3])
    if abs(det) < 1e-12:
        raise ValueError(
            f"`{owner}.affine` is singular (det of its 3x3 part = {det:.3g}); "
            "a voxel-to-world affine needs non-zero voxel sizes."
        )


def voxel_sizes(affine: np.ndarray) -> np.ndarray:
    """Voxel edge lengths in mm (the column norms of the affine's 3x3 part), shape (3,)."""
    return np.sqrt((np.asarray(affine)[:3, :3] ** 2).sum(axis=0))


def default_affine(voxel_mm: float | tuple[float, float, float], shape: tuple[int, int, int]) -> np.ndarray:
    """A RAS affine with the given voxel size that puts the grid's centre at world (0, 0, 0)."""
    vox = np.broadcast_to(np.asarray(voxel_mm, dtype=np.float64), (3,))
    affine = np.diag([*vox, 1.0])
    affine[:3, 3] = -vox * (np.asarray(shape, dtype=np.float64) - 1) / 2
    return affine


def add_scanner_noise(data: np.ndarray, sd: float, modality: str, rng: np.random.Generator) -> np.ndarray:
    """`data` with scanner noise of standard deviation `sd` (in the data's units) added.

    MRI ("mri"): Rician magnitude noise, |data + n_re + i n_im| with n ~ N(0, sd^2) per channel
    (Gudbjartsson & Patz 1995, MRM 34:910); its mean over pure noise is sd * sqrt(pi / 2).
    CT ("ct"): additive Gaussian noise. `sd` = 0 returns `data` unchanged (no draws are made).
    """
    if modality not in ("mri", "ct"):
        raise ValueError(f"`modality` must be 'mri' or 'ct', got {modality!r}.")
    if not sd >= 0:
        raise ValueError(f"`sd` must be >= 0, got {sd!r}.")
    if sd == 0:
        return data
    if modality == "mri":
        re_part = data + sd * rng.standard_normal(np.shape(data))
        return np.hypot(re_part, sd * rng.standard_normal(np.shape(data)))
    return data + sd * rng.standard_normal(np.shape(data))


class Volume(eqx.Module):
    """A scalar 3D image (float64) and its voxel-to-world affine (mm, RAS).

    Arguments:
        data: (x, y, z) finite intensities (MRI arbitrary units, CT Hounsfield units).
        affine: (4, 4) voxel index -> world mm.
    """

    data: np.ndarray
    affine: np.ndarray

    def __init__(self, data, affine):
        self.data = np.asarray(data, dtype=np.float64)
        self.affine = np.asarray(affine, dtype=np.float64)

    def __check_init__(self):
        if self.data.ndim != 3:
            raise ValueError(
                f"`Volume.data` must be 3D (x, y, z), got shape {self.data.shape}; "
                "squeeze a single-volume 4D image or pick one volume first."
            )
        if min(self.data.shape) < 2:
            raise ValueError(f"`Volume.data` has shape {self.data.shape}; every axis needs >= 2 voxels.")
        if not np.all(np.isfinite(self.data)):
            n = int((~np.isfinite(self.data)).sum())
            raise ValueError(
                f"`Volume.data` has {n} NaN/Inf voxels; replace them (e.g. np.nan_to_num) "
                "before building a Volume."
            )
        check_affine(self.affine, "Volume")

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.data.shape

    @property
    def voxel_mm(self) -> np.ndarray:
        return voxel_sizes(self.affine)


class LabelMap(eqx.Module):
    """Integer Tissue labels on a voxel grid, with the voxel-to-world affine (mm, RAS).

    Arguments:
        labels: (x, y, z) integers in 0..4 (`Tissue` values; 0 = background).
        affine: (4, 4) voxel index -> world mm.
    """

    labels: np.ndarray
    affine: np.ndarray

    def __init__(self, labels, affine):
        labels = np.asarray(labels)
        if labels.dtype.kind == "f":
            if not np.all(np.isfinite(labels)) or not np.all(labels == np.round(labels)):
                raise ValueError(
                    "`LabelMap.labels` has non-integer values; pass integer Tissue labels 0..4."
                )
        elif labels.dtype.kind not in "iub":
            raise ValueError(f"`LabelMap.labels` must be integers, got dtype {labels.dtype}.")
        self.labels = labels.astype(np.uint8) if labels.size == 0 or (
            labels.min() >= 0 and labels.max() <= 255) else labels.astype(np.int64)
        self.affine = np.asarray(affine, dtype=np.float64)

    def __check_init__(self):
        if self.labels.ndim != 3:
            raise ValueError(f"`LabelMap.labels` must be 3D (x, y, z), got shape {self.labels.shape}.")
        lo, hi = int(self.labels.min()), int(self.labels.max())
        if lo < 0 or hi > max(Tissue):
            bad = np.unique(self.labels[(self.labels < 0) | (self.labels > max(Tissue))])
            raise ValueError(
                f"`LabelMap.labels` has values {bad[:10].tolist()} outside 0..{int(max(Tissue))}; "
                f"use Tissue values ({', '.join(f'{t.value}={t.name}' for t in Tissue)})."
            )
        check_affine(self.affine, "LabelMap")

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.labels.shape

    @property
    def voxel_mm(self) -> np.ndarray:
        return voxel_sizes(self.affine)

    def mask(self, tissue: Tissue | str | int) -> np.ndarray:
        """Boolean mask of one tissue."""
        return self.labels == int(Tissue.parse(tissue))

    def tissue_volumes_mm3(self) -> dict[Tissue, float]:
        """Volume of each tissue in mm^3 (voxel count times voxel volume)."""
        vox = abs(float(np.linalg.det(self.affine[:3, :3])))
        counts = np.bincount(self.labels.ravel().astype(np.int64), minlength=len(Tissue))
        return {t: float(counts[int(t)]) * vox for t in Tissue if t != Tissue.BACKGROUND}
