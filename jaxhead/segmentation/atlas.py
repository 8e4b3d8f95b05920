"""Probabilistic atlases: a template image and one prior probability map per tissue class.  [host + jax]

An atlas is built as the seed built its CT atlas from manual segmentations (Vonach et al. 2012): every
labelled example is registered affinely to a reference, its intensities and one-hot labels are
resampled (trilinearly, so boundaries become partial-volume fractions) onto the reference grid, and
the results are averaged. A second round registers the examples to the first round's mean template,
which removes the bias towards the reference subject (group-wise averaging, as in the construction
of the ICBM/MNI templates).

Affine registration only, on purpose: the spread of the aligned examples *is* the prior's
uncertainty, which the EM's relaxation and MRF then resolve; a non-linear atlas would be over-
confident about the anatomy of the examples.

The default atlas of each modality is built from real anatomy installed with the package registries
(`templates.mni152_anatomy`: the MNI152 ICBM 2009a brain from nilearn in fsaverage's inner skull and
scalp from MNE; `default_atlas(atlas="mni152")`); the phantom atlas, built from a phantom population
(`jaxhead.phantom`), is there when asked for (`atlas="phantom"`). Both are built at first use and cached as .npz under ``$XDG_CACHE_HOME/jaxhead`` (or ``~/.cache/jaxhead``), written
atomically; it needs no network.
"""

from __future__ import annotations

import functools
import logging
import os
from pathlib import Path
from typing import Literal, Sequence

import equinox as eqx
import numpy as np

from .._files import atomic_write_path
from ..phantom import make_population
from ..tissue import Tissue
from ..volume import LabelMap, Volume, check_affine
from .register import RegisterConfig, register, resample
from .templates import UNMODELLED_CLASSES, atlas_sources, mni152_anatomy

log = logging.getLogger(__name__)

Modality = Literal["mri", "ct"]
MODALITIES = ("mri", "ct")
N_CLASSES = len(Tissue)

#: Bump when the default atlas recipe changes (invalidates cached files; the segment stage's resume
#: fingerprint includes it). 3: the unmodelled-bone map (face, skull base, neck) of the mni152 atlas.
ATLAS_VERSION = 3
#: Seeds of the default atlas subjects start here; keep test/evaluation subjects below it.
DEFAULT_ATLAS_SEED = 1000


def check_modality(modality, name: str = "modality") -> str:
    """Validate a modality string ("mri" or "ct", case-insensitive) and return it lower-case."""
    if not isinstance(modality, str) or modality.lower() not in MODALITIES:
        raise ValueError(f"`{name}` must be 'mri' or 'ct', got {modality!r}.")
    return modality.lower()


class Atlas(eqx.Module):
    """A probabilistic atlas: template intensities, class priors, and their voxel -> world affine.

    Arguments:
        template: (x, y, z) mean intensity (MRI: scaled so brain median = 1; CT: Hounsfield units).
        priors: (5, x, y, z) prior probability of each `Tissue` (BACKGROUND, BRAIN, CSF, SKULL,
            SCALP), summing to 1 over the first axis.
        affine: (4, 4) voxel -> world mm (RAS).
        modality: "mri" or "ct".
        n_subjects: number of examples averaged.
        name: where the atlas comes from (e.g. "mni152", "phantom"), for reports.
        unmodelled: optional (x, y, z) in [0, 1]: where the atlas's source does not model bone (the
            mni152 atlas: face, skull base under the cranial floor, neck); its skull and scalp
            priors there are equal placeholders, and `segment` learns the proportion of the
            UNMODELLED_CLASSES there from the scan (`regional_proportions`). None: nowhere.
    """

    template: np.ndarray
    priors: np.ndarray
    affine: np.ndarray
    modality: str = eqx.field(static=True)
    n_subjects: int = eqx.field(static=True, default=1)
    name: str = eqx.field(static=True, default="custom")
    unmodelled: np.ndarray | None = None

    def __init__(self, template, priors, affine, modality, n_subjects=1, name="custom", unmodelled=None):
        self.template = np.asarray(template, dtype=np.float64)
        self.priors = np.asarray(priors, dtype=np.float32)
        self.affine = np.asarray(affine, dtype=np.float64)
        self.modality = check_modality(modality)
        self.n_subjects = int(n_subjects)
        self.name = str(name)
        self.unmodelled = None if unmodelled is None else np.asarray(unmodelled, dtype=np.float32)

    def __check_init__(self):
        if self.template.ndim != 3:
            raise ValueError(f"`Atlas.template` must be 3D (x, y, z), got shape {self.template.shape}.")
        if self.priors.shape != (N_CLASSES, *self.template.shape):
            raise ValueError(
                f"`Atlas.priors` has shape {self.priors.shape} but the template is {self.template.shape}; "
                f"pass one prior per Tissue class ({N_CLASSES}, *template.shape), ordered "
                f"{[t.name for t in Tissue]}."
            )
        if not np.all(np.isfinite(self.template)) or not np.all(np.isfinite(self.priors)):
            raise ValueError("`Atlas` template or priors contain NaN/Inf.")
        if self.priors.min() < -1e-6:
            raise ValueError(f"`Atlas.priors` has negative values (min {self.priors.min():.3g}); priors are probabilities.")
        s = self.priors.sum(0)
        if np.abs(s - 1).max() > 1e-3:
            raise ValueError(
                f"`Atlas.priors` must sum to 1 over classes at every voxel (max deviation "
                f"{np.abs(s - 1).max():.3g}); normalise them with priors / priors.sum(0)."
            )
        check_affine(self.affine, "Atlas")
        u = self.unmodelled
        if u is not None and (u.shape != self.template.shape or not np.all(np.isfinite(u)) or u.min() < 0
                              or u.max() > 1):
            raise ValueError(
                f"`Atlas.unmodelled` must be a map in [0, 1] of the template's shape {self.template.shape}, got "
                f"shape {u.shape}" + (f", range {u.min():.3g}..{u.max():.3g}" if u.size else "") + "; or pass None."
            )

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.template.shape

    def template_volume(self) -> Volume:
        """The template as a Volume (for registration)."""
        return Volume(self.template, self.affine)

    def save(self, path) -> Path:
        """Write the atlas to an .npz file atomically (`jaxhead.io.atomic_write_path`)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        extra = {} if self.unmodelled is None else {"unmodelled": self.unmodelled.astype(STORED_DTYPE)}
        with atomic_write_path(path) as tmp:
            np.savez_compressed(
                tmp, template=self.template.astype(np.float32), priors=self.priors.astype(STORED_DTYPE),
                affine=self.affine, modality=np.array(self.modality), n_subjects=np.array(self.n_subjects),
                version=np.array(ATLAS_VERSION), name=np.array(self.name), **extra,
            )
        return path

    @classmethod
    def load(cls, path) -> "Atlas":
        """Read an atlas written by `Atlas.save`."""
        with np.load(path) as z:
            name = str(z["name"]) if "name" in z else "custom"
            u = _from_stored_unmodelled(z["unmodelled"]) if "unmodelled" in z else None
            return cls(z["template"], _from_stored_priors(z["priors"]), z["affine"], str(z["modality"]),
                       int(z["n_subjects"]), name, u)

    def stored(self) -> "Atlas":
        """This atlas as `save` then `load` return it (template float32, priors and the unmodelled map
        through float16), without a file; `default_atlas(..., cache=False)` returns this, so that it
        gives the atlas a cached call gives."""
        u = None if self.unmodelled is None else _from_stored_unmodelled(self.unmodelled.astype(STORED_DTYPE))
        return Atlas(self.template.astype(np.float32), _from_stored_priors(self.priors.astype(STORED_DTYPE)),
                     self.affine, self.modality, self.n_subjects, self.name, u)


#: The storage type of an atlas file's priors and unmodelled map (`Atlas.save`).
STORED_DTYPE = np.float16


def _from_stored_priors(p: np.ndarray) -> np.ndarray:
    """Priors read back from STORED_DTYPE: float32, renormalised (float16 rounding: |change| < 1e-3)."""
    p = p.astype(np.float32)
    return p / p.sum(0, keepdims=True)


def _from_stored_unmodelled(u: np.ndarray) -> np.ndarray:
    """The unmodelled map read back from STORED_DTYPE: float32, clipped to [0, 1]."""
    return np.clip(u.astype(np.float32), 0, 1)


def _one_hot(labels: np.ndarray) -> np.ndarray:
    return np.stack([(labels == k).astype(np.float32) for k in range(N_CLASSES)])


def _normalise_intensity(volume: Volume, labels: LabelMap, modality: str) -> np.ndarray:
    """MRI: divide by the median brain intensity (arbitrary units -> brain ~ 1). CT: HU as they are."""
    if modality == "ct":
        return volume.data
    brain = volume.data[labels.labels == Tissue.BRAIN]
    scale = float(np.median(brain)) if brain.size else float(np.percentile(volume.data, 99))
    if scale <= 0:
        raise ValueError("cannot normalise an MRI example: its brain median intensity is <= 0.")
    return volume.data / scale


def build_atlas(
    volumes: Sequence[Volume], label_maps: Sequence[LabelMap], reference: Volume, *,
    modality: Modality = "mri", cfg: RegisterConfig | None = None, rounds: int = 2,
) -> Atlas:
    """Build a probabilistic atlas from labelled examples registered affinely to a reference.

    Arguments:
        volumes: n example scans (any grids).
        label_maps: n `LabelMap`s on the same grids as `volumes`.
        reference: Volume defining the atlas grid (voxel size, extent, affine) and the first round's
            registration target (e.g. one of the examples).
        modality: "mri" or "ct" (MRI intensities are normalised to brain median = 1).
        cfg: RegisterConfig (default: affine only, NMI, 8 and 4 mm levels). With `bspline` on, the
            examples are also aligned non-linearly (sharper priors, less of the population's spread).
        rounds: 1 registers to `reference`; each further round registers to the previous mean template.
    Returns:
        Atlas on the reference grid.
    """
    modality = check_modality(modality)
    if len(volumes) != len(label_maps) or len(volumes) == 0:
        raise ValueError(
            f"`volumes` ({len(volumes)}) and `label_maps` ({len(label_maps)}) must be non-empty and the same length."
        )
    for i, (v, lab) in enumerate(zip(volumes, label_maps)):
        if not isinstance(v, Volume) or not isinstance(lab, LabelMap):
            raise ValueError(f"example {i}: pass a Volume and a LabelMap, got {type(v).__name__}, {type(lab).__name__}.")
        if v.shape != lab.shape or not np.allclose(v.affine, lab.affine):
            raise ValueError(f"example {i}: the LabelMap grid {lab.shape} does not match its Volume {v.shape}.")
    if not isinstance(reference, Volume):
        raise ValueError(f"`reference` must be a Volume, got {type(reference).__name__}.")
    if rounds < 1:
        raise ValueError(f"`rounds` must be >= 1, got {rounds}.")
    cfg = cfg or RegisterConfig(bspline=False)
    target = reference
    # Edge-pad every example at the high end to one common shape: the same voxels keep the same
    # world positions, sampling (mode "nearest") is unchanged, and the registration compiles once.
    common = tuple(max(v.shape[k] for v in volumes) for k in range(3))

    def pad(a):
        return np.pad(a, [(0, c - n) for c, n in zip(common, a.shape)], mode="edge")

    normed = [pad(_normalise_intensity(v, lab, modality)) for v, lab in zip(volumes, label_maps)]
    label_maps = [LabelMap(pad(lab.labels), lab.affine) for lab in label_maps]
    for rnd in range(rounds):
        template = np.zeros(reference.shape)
        priors = np.zeros((N_CLASSES, *reference.shape), np.float32)
        for i, (v, lab, data) in enumerate(zip(volumes, label_maps, normed)):
            t = register(target, Volume(data, v.affine), cfg)
            template += np.asarray(resample(data, v.affine, t, reference.shape, reference.affine))
            priors += np.asarray(resample(_one_hot(lab.labels), v.affine, t, reference.shape, reference.affine),
                                 dtype=np.float32)
            log.info("atlas round %d: example %d registered", rnd + 1, i)
        template /= len(volumes)
        priors /= len(volumes)
        target = Volume(template, reference.affine)
    priors = np.clip(priors, 0, None)
    priors /= priors.sum(0, keepdims=True)
    return Atlas(template, priors, reference.affine, modality, len(volumes))


def pad_volume(volume: Volume, margin_mm: float) -> Volume:
    """A Volume grown by `margin_mm` of edge-replicated voxels on every side (same voxel size).

    Used to give an atlas grid room for subjects larger than its reference.
    """
    vox = np.sqrt((volume.affine[:3, :3] ** 2).sum(0))
    n = np.ceil(margin_mm / vox).astype(int)
    data = np.pad(volume.data, [(k, k) for k in n], mode="edge")
    affine = volume.affine.copy()
    affine[:3, 3] = volume.affine[:3, :3] @ (-n) + volume.affine[:3, 3]
    return Volume(data, affine)


def regional_proportions(likelihoods, weights, *, tol: float = 1e-7, max_iter: int = 500) -> np.ndarray:
    """Maximum-likelihood proportions of classes in a region, given each voxel's class likelihoods.

    The EM for the weights of a mixture whose components are fixed (Dempster, Laird & Rubin 1977;
    McLachlan & Peel 2000, sec. 2.8): q_ik = pi_k l_ik / sum_j pi_j l_ij, then
    pi_k = sum_i w_i q_ik / sum_i w_i, from equal shares until pi changes by less than `tol`.

    Arguments:
        likelihoods: (C, ...) class likelihoods l_ik >= 0 (any common scale per voxel, e.g. the
            posteriors under a uniform prior).
        weights: (...) voxel weights w_i >= 0 (how much each voxel belongs to the region).
    Returns:
        (C,) proportions summing to 1; equal shares where the region is empty.
    """
    lik = np.asarray(likelihoods, np.float64).reshape(len(likelihoods), -1)
    w = np.asarray(weights, np.float64).ravel()
    if lik.shape[1] != w.size:
        raise ValueError(f"`likelihoods` {np.shape(likelihoods)} and `weights` {np.shape(weights)} do not match.")
    keep = (w > 0) & (lik.sum(0) > 0)
    lik, w = lik[:, keep], w[keep]
    pi = np.full(len(lik), 1.0 / len(lik))
    if not w.sum() > 0:
        return pi
    lik = lik / lik.sum(0)  # per-voxel scale is irrelevant; this keeps the sums well conditioned
    for _ in range(max_iter):
        q = pi[:, None] * lik
        q /= q.sum(0)
        new = (q * w).sum(1) / w.sum()
        done = np.abs(new - pi).max() < tol
        pi = new
        if done:
            break
    return pi


def with_proportions(priors, unmodelled, proportions, classes=UNMODELLED_CLASSES) -> np.ndarray:
    """Priors whose `classes` share their mass s in the unmodelled region as `proportions`:
    p_k <- (1 - u) p_k + u pi_k s (k in classes; other classes and the sum unchanged). Float32 priors
    stay float32 (a 1 mm head's priors are 140 MB in float32), others are computed in float64. Only the
    voxels with u > 0 are computed (where u = 0 the formula returns p_k exactly): about a third of a
    head's grid, 0.2 s instead of 0.46 s on a 1 mm head (benchmarks/segment.py's)."""
    dtype = np.float32 if np.asarray(priors).dtype == np.float32 else np.float64
    p = np.array(priors, dtype=dtype, copy=True)
    k = [int(c) for c in classes]
    u = np.asarray(unmodelled, dtype).ravel()
    flat = p.reshape(len(p), -1)
    if u.size != flat.shape[1]:
        raise ValueError(f"with_proportions: `unmodelled` {np.shape(unmodelled)} does not match the priors' grid "
                         f"{p.shape[1:]}; resample it onto the priors' grid first.")
    at = np.flatnonzero(u)
    uk, pi = u[at], np.asarray(proportions, dtype)
    sub = [flat[c, at] for c in k]  # row by row: a (len(k), n) gather and scatter cost three times as much
    total = functools.reduce(np.add, sub)
    for c, row, share in zip(k, sub, pi):
        flat[c, at] = (1 - uk) * row + uk * share * total
    return p


def cache_dir() -> Path:
    """The user cache folder of jaxhead: $XDG_CACHE_HOME/jaxhead or ~/.cache/jaxhead."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxhead"


ATLAS_KINDS = ("mni152", "phantom")


def check_atlas_kind(kind, name: str = "atlas") -> str:
    """Validate an atlas source name ("mni152" or "phantom")."""
    if not isinstance(kind, str) or kind.lower() not in ATLAS_KINDS:
        raise ValueError(
            f"`{name}` must be one of {ATLAS_KINDS} ('mni152': real anatomy, the default; 'phantom': "
            f"jaxhead's synthetic heads, for tests and the synthetic demo), got {kind!r}."
        )
    return kind.lower()


def anatomy_atlas(anatomy, modality: Modality = "mri", *, voxel_mm: float = 2.0, name: str | None = None) -> Atlas:
    """An atlas of one real anatomy (`jaxhead.segmentation.templates.Anatomy`) at `voxel_mm`.

    Priors: the anatomy's class fractions blurred by 3 mm plus a 5 % share of every head tissue
    (`templates.atlas_priors`); template: a synthesised scan of the modality (`templates.render`);
    `unmodelled`: where the anatomy does not model bone (`templates.unmodelled_map`).
    """
    modality = check_modality(modality)
    template, priors, affine, unmodelled = atlas_sources(anatomy, modality, voxel_mm)
    return Atlas(template, priors, affine, modality, 1, name or anatomy.name, unmodelled)


def default_atlas(
    modality: Modality = "mri", *, atlas: str = "mni152", voxel_mm: float = 2.0, n_subjects: int = 8,
    seed: int = DEFAULT_ATLAS_SEED, cache: bool = True,
) -> Atlas:
    """The default atlas of a modality, built on first use and cached on disk.

    Arguments:
        modality: "mri" or "ct".
        atlas: "mni152" (default): real anatomy, the ICBM 2009a MNI152 brain (nilearn) in
            fsaverage's inner skull and scalp (MNE), `templates.mni152_anatomy`; "phantom":
            averaged `jaxhead.phantom` subjects (tests, the synthetic demo).
        voxel_mm: atlas voxel size in mm.
        n_subjects, seed: phantom atlas only: subjects averaged (seeds seed .. seed + n_subjects - 1;
            default 1000, disjoint from evaluation subjects 0..999).
        cache: read/write the cache file under `cache_dir()`.
    Returns:
        Atlas (its `name` says which); built in seconds (mni152) to about a minute (phantom, 2 mm)
        on first use, then loaded from the cache.
    """
    modality = check_modality(modality)
    kind = check_atlas_kind(atlas)
    if not voxel_mm > 0 or n_subjects < 1:
        raise ValueError(f"`voxel_mm` must be > 0 and `n_subjects` >= 1, got {voxel_mm}, {n_subjects}.")
    if kind == "phantom":
        name = f"atlas_{modality}_{voxel_mm:g}mm_n{n_subjects}_s{seed}_v{ATLAS_VERSION}.npz"
    else:
        name = f"atlas_{kind}_{modality}_{voxel_mm:g}mm_v{ATLAS_VERSION}.npz"
    path = cache_dir() / name
    if cache and path.exists():
        try:
            return Atlas.load(path)
        except Exception as err:  # a corrupt cache file is rebuilt, and said so
            log.warning("atlas cache %s unreadable (%s); rebuilding it", path, err)

    if kind == "phantom":
        log.info("building the phantom %s atlas from %d phantom subjects at %g mm", modality, n_subjects, voxel_mm)
        pop = make_population(n_subjects, modality, seed=seed, voxel_mm=voxel_mm)
        vols = [v for v, _ in pop]
        labs = [lab for _, lab in pop]
        out = build_atlas(vols, labs, pad_volume(vols[0], 16.0), modality=modality)
        out = Atlas(out.template, out.priors, out.affine, modality, out.n_subjects, "phantom")
    else:
        log.info("building the mni152 %s atlas (MNI152 + fsaverage) at %g mm", modality, voxel_mm)
        out = anatomy_atlas(mni152_anatomy(), modality, voxel_mm=voxel_mm, name="mni152")
    if not cache:
        return out.stored()
    out.save(path)
    log.info("default atlas cached at %s", path)
    return Atlas.load(path)  # what every later call loads, to the bit: a cold cache segments as a warm one
