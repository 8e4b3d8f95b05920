"""Real-anatomy sources for atlases and test heads: MNI152 + fsaverage, JNIfTI maps, scan synthesis.  [host]

An `Anatomy` is a set of six tissue fractions on a voxel grid (air, grey matter, white matter, CSF,
skull, scalp, summing to 1 per voxel). From it come

- the atlas of real anatomy (`atlas_from_anatomy`): priors = the five jaxhead classes (grey + white
  matter = brain), blurred by the population spread a single subject cannot show, plus a small share
  of every head tissue everywhere in the head; template = a synthesised scan (`render` without noise
  or bias), MRI with the real MNI152 T1 inside the brain where it is given;
- test scans (`render`): MRI (T1-like; tissue contrasts, fat/muscle texture of the scalp, Rician
  noise, a smooth multiplicative bias field, all drawn per scan) or CT (Hounsfield units).

The default anatomy (`mni152_anatomy`) is built from data installed with the package registries,
no download:

- nilearn's ICBM 2009a nonlinear symmetric MNI152 T1 and grey/white-matter probability maps
  (Fonov et al. 2011, NeuroImage 54:313; Fonov et al. 2009, NeuroImage 47:S102; files under
  ``nilearn/datasets/data/``, the ICBM 2009 licence: free use with the copyright notice of the
  McConnell Brain Imaging Centre). The T1 there is brain-extracted, so it gives brain and CSF only.
- MNE-Python's fsaverage scalp (``fsaverage-head.fif``) and inner-skull (``fsaverage-inner_skull-bem.fif``)
  surfaces (FreeSurfer fsaverage, Fischl et al. 1999; FreeSurfer licence, redistributed by MNE under
  BSD-3), in FreeSurfer surface RAS = MNI305 space, mapped to MNI152 with FreeSurfer's published
  MNI305 -> MNI152 affine (`MNI305_TO_MNI152`) and rasterised.

Intracranial = inside the inner skull (or brain); brain = grey + white matter probabilities; CSF = the
rest of the intracranial space; skull = the first `skull_mm` outside it, never closer than
`min_scalp_mm` to the scalp surface; scalp = the rest of the head (all soft tissue, face and neck
included). No outer-skull surface ships with either package, hence the fixed thickness: adult
cranial vault thickness averages 6-7 mm (e.g. Lynnerup et al. 2005, Forensic Sci. Int. 147:S37 report
means 6.1-6.7 mm), scaled to the template's larger size (`ADULT_ICV_MM3`). Facial bones, the skull
base below the cranial floor and the vertebrae are not in this anatomy: the soft tissue under or
beside the cranium is marked `unmodelled_bone` (`under_or_beside`), and `segment` learns the share of
bone there from the scan (`atlas.regional_proportions`). Measured before that (ANTs head, MRI, 2 mm):
about 82 % of its missed skull lay > 10 mm from the intracranial space in the face, labelled scalp under
a 1.5 % skull prior.
"""

from __future__ import annotations

import base64
import gzip
import importlib.util
import json
import logging
import os
from pathlib import Path

import equinox as eqx
import mne
import nibabel as nib
import numpy as np
from scipy import ndimage

from ..tissue import Tissue
from ..volume import LabelMap, Volume, add_scanner_noise, voxel_sizes

log = logging.getLogger(__name__)

#: Fine tissues of an Anatomy, in order.
FINE_TISSUES = ("air", "grey_matter", "white_matter", "csf", "skull", "scalp")
#: The jaxhead class (Tissue) of each fine tissue.
FINE_TO_CLASS = (Tissue.BACKGROUND, Tissue.BRAIN, Tissue.BRAIN, Tissue.CSF, Tissue.SKULL, Tissue.SCALP)

#: FreeSurfer's MNI305 -> MNI152 affine (FreeSurfer wiki "CoordinateSystems", item 8: "The transform
#: from MNI305 to MNI152 space"), mm.
MNI305_TO_MNI152 = np.array([
    [0.9975, -0.0073, 0.0176, -0.0429],
    [0.0146, 1.0009, -0.0024, 1.5496],
    [-0.0130, -0.0093, 0.9971, 1.1840],
    [0.0, 0.0, 0.0, 1.0],
])

#: T1-weighted MRI intensities relative to white matter = 1 (defaults of `render`, and the ranges the
#: evaluation draws from). Ordering WM > GM > CSF, scalp fat brightest, cortical bone darkest, as
#: in T1-weighted gradient-echo (MPRAGE) images (e.g. Wansapura et al. 1999, JMRI 9:531 for the T1s;
#: bone and air give almost no signal).
MRI_CONTRAST = dict(air=0.0, grey_matter=0.65, white_matter=1.0, csf=0.25, skull=0.12, fat=1.1, muscle=0.55,
                    diploe=0.45)
MRI_CONTRAST_RANGE = dict(air=(0.0, 0.0), grey_matter=(0.55, 0.8), white_matter=(1.0, 1.0), csf=(0.1, 0.4),
                          skull=(0.05, 0.25), fat=(0.8, 1.4), muscle=(0.4, 0.75), diploe=(0.3, 0.6))
#: CT in Hounsfield units: air -1000, fat about -100, CSF 0-15, white matter 20-30, grey matter 35-45,
#: muscle/skin 35-55, cranial bone several hundred (diploe) to 1500-1900 (compact tables)
#: (Buzug 2008, Computed Tomography, Springer, Fig. 1.2; Schneider, Bortfeld & Schlegel 2000, Phys.
#: Med. Biol. 45:459, Table 1). The skull here is one value for the mixture of tables and diploe.
CT_HU = dict(air=-1000.0, grey_matter=40.0, white_matter=28.0, csf=8.0, skull=1000.0, fat=-100.0, muscle=45.0,
             diploe=700.0, table=1700.0)
CT_HU_RANGE = dict(air=(-1000.0, -1000.0), grey_matter=(35.0, 45.0), white_matter=(20.0, 30.0), csf=(0.0, 15.0),
                   skull=(600.0, 1500.0), fat=(-120.0, -60.0), muscle=(35.0, 60.0), diploe=(550.0, 850.0),
                   table=(1500.0, 1900.0))
#: "diploe" (both modalities) and "table" (CT) are drawn only where an Anatomy has a `diploe` map
#: (`with_diploe`): the skull is then marrow ("diploe") between compact tables (CT: "table", compact
#: bone's 1500-1900 HU, in place of the mixture's "skull"; MRI: "skull", already compact bone's). The
#: diploe's intensities are the phantom's (`jaxhead.phantom`: 0.3-0.6 of white matter on T1; 550-850
#: HU), as is the table thickness below (the phantom's outer table 1.2-2.4 mm, inner 0.8-1.6 mm). Both
#: keys come last in the ranges, so `random_contrast` draws the other tissues as before.
#: On T1 that marrow is as dark as a child's red (haematopoietic) marrow; an adult's calvarial marrow is
#: fatty and as bright as fat (`fatty_marrow`).
DIPLOE_TABLE_MM = 1.5


def fatty_marrow(contrast: dict | None = None) -> dict:
    """An MRI contrast (`render`'s; None: MRI_CONTRAST) whose diploe is as bright as its fat: the T1 of an
    adult's calvarial marrow. On T1-weighted images skull marrow becomes isointense with fat (red to
    yellow marrow) at a mean age of 9.7 years in the frontal, 11.0 in the occipital squama and 11.5 in the
    parietal bone (Simonson & Kao 1992, Pediatr. Radiol. 22:556, 324 children); the default "diploe"
    (0.3-0.6 of white matter, below fat's 0.8-1.4) is the darker marrow of younger children."""
    out = dict(MRI_CONTRAST)
    out.update(contrast or {})
    unknown = sorted(set(out) - set(MRI_CONTRAST))
    if unknown:
        raise ValueError(f"fatty_marrow: `contrast` has keys {unknown} that no MRI contrast has "
                         f"({sorted(MRI_CONTRAST)}); pass an MRI contrast (a CT's marrow is not changed).")
    out["diploe"] = out["fat"]
    return out


class Anatomy(eqx.Module):
    """Tissue fractions of a head on a voxel grid.

    Arguments:
        fractions: (6, x, y, z) fractions of FINE_TISSUES (air, grey matter, white matter, CSF, skull,
            scalp), summing to 1 at every voxel.
        affine: (4, 4) voxel -> world mm (RAS).
        name: where it comes from.
        t1: optional (x, y, z) measured T1 image (0 where not given), used in an MRI template.
        unmodelled_bone: optional (x, y, z) in [0, 1]: where the source says nothing about bone, so
            that its soft tissue there is a placeholder, not an observation (the MNI152 + fsaverage
            head has no facial bones, skull base below the cranial floor or vertebrae); an atlas
            built from it gives skull and scalp equal priors there (`atlas_priors`). None: the
            anatomy is complete.
        diploe: optional (x, y, z): the share of each voxel that is diploe (marrow between the skull's
            tables; part of its skull fraction, 0..fractions[4]); `render` gives it the contrast's
            "diploe" value (`with_diploe`). None: the skull is one tissue.
    """

    fractions: np.ndarray
    affine: np.ndarray
    name: str = eqx.field(static=True)
    t1: np.ndarray | None = None
    unmodelled_bone: np.ndarray | None = None
    diploe: np.ndarray | None = None

    def __check_init__(self):
        if self.fractions.ndim != 4 or self.fractions.shape[0] != len(FINE_TISSUES):
            raise ValueError(f"`Anatomy.fractions` must be (6, x, y, z), got {self.fractions.shape}.")
        for name in ("t1", "unmodelled_bone", "diploe"):
            a = getattr(self, name)
            if a is not None and a.shape != self.fractions.shape[1:]:
                raise ValueError(f"`Anatomy.{name}` has shape {a.shape}, fractions {self.fractions.shape[1:]}.")
        u = self.unmodelled_bone
        if u is not None and not (np.all(np.isfinite(u)) and u.min() >= 0 and u.max() <= 1):
            raise ValueError(
                f"`Anatomy.unmodelled_bone` must lie in [0, 1] (a mask or a fraction), got range "
                f"{np.nanmin(u):.3g}..{np.nanmax(u):.3g}."
            )

        d = self.diploe
        if d is not None and not (np.all(np.isfinite(d)) and d.min() >= 0 and np.all(d <= self.fractions[4] + 1e-5)):
            raise ValueError("`Anatomy.diploe` must lie in [0, the voxel's skull fraction] (it is part of the skull).")

    @property
    def shape(self):
        return self.fractions.shape[1:]

    def class_fractions(self) -> np.ndarray:
        """(5, x, y, z) fractions of the Tissue classes (grey + white matter = brain)."""
        out = np.zeros((len(Tissue), *self.shape), np.float32)
        for f, t in zip(self.fractions, FINE_TO_CLASS):
            out[int(t)] += f
        return out

    def labels(self) -> LabelMap:
        """The tissue filling most of each voxel, as a LabelMap (ties: the lower Tissue value)."""
        return LabelMap(self.class_fractions().argmax(0).astype(np.uint8), self.affine)

    def resampled(self, voxel_mm: float) -> "Anatomy":
        """The anatomy on a grid of `voxel_mm` voxels over the same field of view (fractions averaged).

        Integer multiples of the voxel size are block averages (exact partial volume); other sizes
        interpolate the fractions linearly.
        """
        vox = voxel_sizes(self.affine)
        f = voxel_mm / vox
        if np.allclose(f, 1):
            return self
        if np.allclose(f, np.round(f)) and np.all(np.round(f) >= 1):
            k = np.round(f).astype(int)
            n = np.array(self.shape) // k
            crop = tuple(slice(0, int(a * b)) for a, b in zip(n, k))

            def block(a):
                a = a[crop]
                return a.reshape(n[0], k[0], n[1], k[1], n[2], k[2]).mean((1, 3, 5))

            fr = np.stack([block(a) for a in self.fractions]).astype(np.float32)
            t1, um, dp = (None if a is None else block(a).astype(np.float32)
                          for a in (self.t1, self.unmodelled_bone, self.diploe))
            aff = self.affine.copy()
            aff[:3, :3] = self.affine[:3, :3] * k
            aff[:3, 3] = self.affine[:3, :3] @ ((k - 1) / 2) + self.affine[:3, 3]
        else:
            n = np.maximum(np.floor((np.array(self.shape) - 1) / f).astype(int) + 1, 2)
            idx = np.meshgrid(*[np.arange(m) * s for m, s in zip(n, f)], indexing="ij")
            fr = np.stack([ndimage.map_coordinates(a, idx, order=1, mode="nearest") for a in self.fractions])
            fr = (fr / np.maximum(fr.sum(0, keepdims=True), 1e-12)).astype(np.float32)
            t1, um, dp = (None if a is None else ndimage.map_coordinates(a, idx, order=1, mode="nearest")
                          for a in (self.t1, self.unmodelled_bone, self.diploe))
            if dp is not None:  # the fractions were renormalised; the diploe stays inside the skull
                dp = np.clip(dp, 0.0, fr[4]).astype(np.float32)
            aff = self.affine.copy()
            aff[:3, :3] = self.affine[:3, :3] * f
        return Anatomy(fr, aff, self.name, t1, um, dp)


def with_diploe(anatomy: Anatomy, table_mm: float = DIPLOE_TABLE_MM) -> Anatomy:
    """The anatomy with a diploe: skull more than `table_mm` from every voxel that is not mostly skull.

    The compact tables are the outer `table_mm` of the skull on both sides; where the skull is thinner than
    two tables it has no diploe. Computed on the anatomy's own grid (use the source's finest grid, then
    `resampled`, so the diploe's partial volume is averaged like the fractions).

    Arguments:
        anatomy: Anatomy (its `diploe` is replaced).
        table_mm: thickness of each table, mm (> 0).
    Returns:
        Anatomy with `diploe` = skull fraction where the depth into the skull exceeds `table_mm`.
    """
    if not (np.isfinite(table_mm) and table_mm > 0):
        raise ValueError(f"`table_mm` must be > 0 (mm), got {table_mm}.")
    skull = anatomy.fractions[4]
    depth = ndimage.distance_transform_edt(skull > 0.5, sampling=voxel_sizes(anatomy.affine))
    diploe = np.where(depth > table_mm, skull, 0.0).astype(np.float32)
    return Anatomy(anatomy.fractions, anatomy.affine, anatomy.name, anatomy.t1, anatomy.unmodelled_bone, diploe)


# ----------------------------------------------------------------------------------------------
# sources
# ----------------------------------------------------------------------------------------------


#: `on_scan_grid`: air kept above the top of the head (voxels): a scan's field of view leaves some above it
SCAN_TOP_MARGIN_VOX = 5


def on_scan_grid(anatomy: Anatomy, shape, top_margin_vox: int = SCAN_TOP_MARGIN_VOX) -> Anatomy:
    """`anatomy` on a grid of `shape` with the same voxels, placed as a head scan's field of view is: the head
    (voxels that are not all air) centred left-right and front-back, its top `top_margin_vox` voxels below the
    grid's top, and whatever does not fit cut off (the neck below, the nose or the back of the head where the
    grid is shorter front to back). Padding is air. Every kept voxel keeps its world position (the affine's
    origin moves) and its fractions, T1, unmodelled-bone and diploe values.

    Arguments:
        anatomy: Anatomy, axes ordered (left-right, back-front, bottom-top) as the shipped heads are.
        shape: (3,) the grid's voxels.
        top_margin_vox: air voxels kept above the head.
    Returns:
        Anatomy of `shape`.
    """
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"on_scan_grid: `shape` must be three positive voxel counts, got {shape}.")
    head = np.nonzero(np.asarray(anatomy.fractions[0]) < 1.0 - 1e-6)
    if not head[0].size:
        raise ValueError("on_scan_grid: the anatomy is all air; there is no head to place.")
    lo, hi = [int(h.min()) for h in head], [int(h.max()) for h in head]
    # start: the source index of the grid's first voxel along each axis (negative: padding before it)
    start = [(lo[a] + hi[a] + 1 - shape[a]) // 2 for a in (0, 1)] + [hi[2] + 1 + top_margin_vox - shape[2]]
    src, dst = [], []
    for a in range(3):
        first, last = max(start[a], 0), min(start[a] + shape[a], anatomy.shape[a])
        src.append(slice(first, max(last, first)))
        dst.append(slice(first - start[a], max(last, first) - start[a]))
    src, dst = tuple(src), tuple(dst)

    def placed(a):
        if a is None:
            return None
        a = np.asarray(a)
        out = np.zeros(a.shape[:-3] + shape, a.dtype)
        out[(Ellipsis,) + dst] = a[(Ellipsis,) + src]
        return out

    fractions = placed(anatomy.fractions)
    fractions[0][fractions.sum(0) == 0] = 1.0  # the padding is air
    affine = np.array(anatomy.affine, np.float64, copy=True)
    affine[:3, 3] = affine[:3, :3] @ np.asarray(start, np.float64) + affine[:3, 3]
    return Anatomy(fractions, affine, f"{anatomy.name} on a {'x'.join(map(str, shape))} grid",
                   placed(anatomy.t1), placed(anatomy.unmodelled_bone), placed(anatomy.diploe))


def _package_file(package: str, *parts: str) -> Path:
    """A data file shipped inside an installed package (located without importing the package)."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(
            f"the real-anatomy atlas needs `{package}` (pip install nilearn mne); or pass "
            "SegmentConfig(atlas='phantom')."
        )
    path = Path(list(spec.submodule_search_locations)[0]).joinpath(*parts)
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing from the installed `{package}`; reinstall it.")
    return path


def _read_bem(path: Path) -> tuple[np.ndarray, np.ndarray]:
    surf = mne.read_bem_surfaces(str(path), verbose=False)[0]  # mne loads its submodules lazily
    return np.asarray(surf["rr"], np.float64) * 1000.0, np.asarray(surf["tris"], np.int64)


def rasterise(vertices: np.ndarray, triangles: np.ndarray, shape, affine: np.ndarray) -> np.ndarray:
    """Voxel centres inside a closed triangle surface (ray parity along the grid's third axis).

    Arguments:
        vertices: (n, 3) world mm.
        triangles: (m, 3) vertex indices of a closed (watertight) surface.
        shape: (x, y, z) grid.
        affine: (4, 4) voxel -> world mm; axis-aligned (diagonal 3x3 part).
    Returns:
        (x, y, z) bool.
    """
    a = np.asarray(affine, np.float64)
    if np.abs(a[:3, :3] - np.diag(np.diag(a[:3, :3]))).max() > 1e-9:
        raise ValueError("`affine` of `rasterise` must be axis-aligned (diagonal 3x3 part).")
    v = (np.asarray(vertices, np.float64) - a[:3, 3]) / np.diag(a[:3, :3])  # voxel index space
    v[:, :2] += 1e-4  # rays through x, y grid points; shift the surface off them (no edge hits)
    t = v[np.asarray(triangles)]  # (m, 3, 3)
    lo = np.ceil(t[:, :, :2].min(1)).astype(int)
    hi = np.floor(t[:, :, :2].max(1)).astype(int)
    counts = np.zeros((shape[0], shape[1], shape[2] + 1), np.int32)
    # candidate (triangle, i, j) pairs: every grid column in each triangle's bounding box
    nx = np.clip(hi[:, 0] - lo[:, 0] + 1, 0, None)
    ny = np.clip(hi[:, 1] - lo[:, 1] + 1, 0, None)
    n = nx * ny
    tri = np.repeat(np.arange(len(t)), n)
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    i = lo[tri, 0] + k // np.maximum(ny[tri], 1)
    j = lo[tri, 1] + k % np.maximum(ny[tri], 1)
    p0, p1, p2 = t[tri, 0], t[tri, 1], t[tri, 2]
    d1, d2 = p1[:, :2] - p0[:, :2], p2[:, :2] - p0[:, :2]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    ok = np.abs(det) > 1e-12
    q = np.stack([i, j], 1) - p0[:, :2]
    det_safe = np.where(ok, det, 1.0)  # triangles seen edge-on (det 0) never count
    u = (q[:, 0] * d2[:, 1] - q[:, 1] * d2[:, 0]) / det_safe
    w = (d1[:, 0] * q[:, 1] - d1[:, 1] * q[:, 0]) / det_safe
    ok &= (u >= 0) & (w >= 0) & (u + w <= 1)
    z = p0[:, 2] + u * (p1[:, 2] - p0[:, 2]) + w * (p2[:, 2] - p0[:, 2])
    ok &= (i >= 0) & (i < shape[0]) & (j >= 0) & (j < shape[1])
    zi = np.clip(np.ceil(z[ok]).astype(int), 0, shape[2])  # voxels k >= z are past this crossing
    np.add.at(counts, (i[ok], j[ok], zi), 1)
    return (np.cumsum(counts, axis=2)[..., : shape[2]] % 2) == 1


#: Adult total intracranial volume, mm^3: about 1.45 L on average (adult range roughly 1.2-1.7 L;
#: e.g. Buckner et al. 2004, NeuroImage 23:724). The MNI152 template is larger than a native head, so
#: native thicknesses are scaled by (template ICV / this)^(1/3) in `mni152_anatomy`.
ADULT_ICV_MM3 = 1.45e6


def under_or_beside(mask: np.ndarray) -> np.ndarray:
    """Voxels not above `mask` along the grid's third axis: below the lowest `mask` voxel of their
    column, or in a column `mask` does not reach.

    With a RAS-aligned grid (third axis superior) and `mask` the intracranial space, this is the part
    of the head under the cranial floor (skull base, face, neck) or beside the cranium (in front of
    the forehead, behind the occiput, the temples), where a shell around the intracranial space is
    not a model of the bone.
    """
    m = np.asarray(mask, bool)
    if m.ndim != 3:
        raise ValueError(f"`mask` of `under_or_beside` must be 3D, got shape {m.shape}.")
    floor = np.where(m.any(2), m.argmax(2), m.shape[2])  # first mask voxel from below; none: all
    return np.arange(m.shape[2])[None, None, :] < floor[:, :, None]


def mni152_anatomy(*, skull_mm: float = 6.5, min_scalp_mm: float = 2.0) -> Anatomy:
    """The MNI152 (ICBM 2009a) brain in fsaverage's inner skull and scalp, 1 mm (see module docstring).

    Arguments:
        skull_mm: skull thickness outside the inner-skull surface, mm in a native (average adult) head;
            scaled to MNI152 space by the cube root of its intracranial volume over ADULT_ICV_MM3.
        min_scalp_mm: the skull stops this far inside the scalp surface, native mm (scaled alike).
    Returns:
        Anatomy on a 1 mm grid in MNI152 space, cut just above the bottom of fsaverage's neck (so that
        edge-replicating the grid continues the neck downwards), with the measured T1, and the soft
        tissue under or beside the cranium (outside the skull shell, deeper than `min_scalp_mm`
        below the scalp surface) marked `unmodelled_bone`: facial bones, the skull base below the
        cranial floor and the vertebrae lie there in a real head, and neither package gives them.
    """
    data = _package_file("nilearn", "datasets", "data")
    imgs = {k: nib.load(data / f"mni_icbm152_{k}_tal_nlin_sym_09a_converted.nii.gz") for k in ("t1", "gm", "wm")}
    aff_mni = imgs["t1"].affine
    if not np.allclose(aff_mni[:3, :3], np.eye(3)):
        raise ValueError(
            f"the installed nilearn's MNI152 T1 has affine {aff_mni[:3, :3].tolist()}; this build expects the "
            "1 mm RAS grid nilearn >= 0.14 ships. Install nilearn >= 0.14, or pass SegmentConfig(atlas='phantom')."
        )
    head_v, head_t = _read_bem(_package_file("mne", "data", "fsaverage", "fsaverage-head.fif"))
    skull_v, skull_t = _read_bem(_package_file("mne", "data", "fsaverage", "fsaverage-inner_skull-bem.fif"))
    to152 = lambda p: p @ MNI305_TO_MNI152[:3, :3].T + MNI305_TO_MNI152[:3, 3]  # noqa: E731
    head_v, skull_v = to152(head_v), to152(skull_v)
    # grid: 1 mm, aligned with the MNI152 grid, covering the head with 8 mm of air, bottom just
    # above the lowest scalp point (the neck is cut there)
    lo = np.floor(head_v.min(0)) - 8
    hi = np.ceil(head_v.max(0)) + 8
    lo[2] = np.ceil(head_v[:, 2].min()) + 6
    lo = np.minimum(lo, aff_mni[:3, 3])
    hi = np.maximum(hi, aff_mni[:3, :3] @ (np.array(imgs["t1"].shape) - 1) + aff_mni[:3, 3])
    shape = tuple(int(n) for n in hi - lo + 1)
    affine = np.eye(4)
    affine[:3, 3] = lo
    off = np.round(aff_mni[:3, 3] - lo).astype(int)

    def embed(img):
        out = np.zeros(shape, np.float32)
        a = np.asarray(img.get_fdata(), np.float32)
        out[off[0]:off[0] + a.shape[0], off[1]:off[1] + a.shape[1], off[2]:off[2] + a.shape[2]] = a
        return out

    t1, gm, wm = embed(imgs["t1"]), embed(imgs["gm"]) / 255.0, embed(imgs["wm"]) / 255.0
    inner = rasterise(skull_v, skull_t, shape, affine)
    head = rasterise(head_v, head_t, shape, affine)
    brain = np.clip(gm + wm, 0.0, 1.0)
    intracranial = inner | (brain > 0.5)
    brain = np.where(intracranial, brain, 0.0)
    gm_share = np.where(gm + wm > 0, gm / np.maximum(gm + wm, 1e-6), 0.0)
    scale = (intracranial.sum() / ADULT_ICV_MM3) ** (1 / 3)  # 1 mm^3 voxels
    skull_mm, min_scalp_mm = skull_mm * scale, min_scalp_mm * scale
    log.info("mni152 anatomy: intracranial %.2f L, native -> MNI152 scale %.3f, skull %.1f mm",
             intracranial.sum() / 1e6, scale, skull_mm)
    head |= ndimage.binary_dilation(intracranial, iterations=int(np.ceil(skull_mm + min_scalp_mm)))
    d_out = ndimage.distance_transform_edt(~intracranial)  # mm (1 mm grid)
    d_scalp = ndimage.distance_transform_edt(head)
    skull = ~intracranial & head & (d_out <= skull_mm) & (d_scalp > min_scalp_mm)
    fr = np.zeros((6, *shape), np.float32)
    fr[1] = brain * gm_share
    fr[2] = brain * (1 - gm_share)
    fr[3] = np.where(intracranial, 1.0 - brain, 0.0)
    fr[4] = skull
    fr[5] = head & ~intracranial & ~skull
    fr[0] = ~head
    t1 = np.where(intracranial, t1, 0.0).astype(np.float32)
    unmodelled = head & ~intracranial & ~skull & (d_scalp > min_scalp_mm) & under_or_beside(intracranial)
    return Anatomy(fr, affine, "mni152", t1, unmodelled.astype(np.float32))


def read_jnifti(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a JNIfTI text file (.jnii) with gzip-compressed data: (array, (4, 4) affine).

    The array is in the row-major order of `_ArraySize_`, scaled by the header's ScaleSlope.
    """
    j = json.loads(Path(path).read_text(), strict=False)  # the header holds a raw control character
    h, d = j["NIFTIHeader"], j["NIFTIData"]
    if d.get("_ArrayZipType_") != "gzip":
        raise ValueError(f"{path}: only gzip-compressed JNIfTI data is supported, got {d.get('_ArrayZipType_')!r}.")
    raw = gzip.decompress(base64.b64decode(d["_ArrayZipData_"]))
    a = np.frombuffer(raw, dtype=np.dtype(d["_ArrayType_"])).reshape(d["_ArraySize_"])
    slope = float(h.get("ScaleSlope") or 1.0)
    affine = np.eye(4)
    affine[:3] = np.asarray(h["Affine"], np.float64)
    return a.astype(np.float32) * slope, affine


def shipped_heads_folder() -> Path:
    """Where the shipped anatomy lies (the ANTs head's c1..c6 .jnii): $JAXHEAD_HEADS, else shared/data/heads in
    the first folder above this package that has one (../shared/data/heads beside a checkout, one folder deeper
    for a worktree), else ../shared/data/heads. Only a path: nothing is read or checked here."""
    if env := os.environ.get("JAXHEAD_HEADS"):
        return Path(env)
    return next((p / "shared" / "data" / "heads" for p in Path(__file__).resolve().parents
                 if (p / "shared" / "data" / "heads").is_dir()), Path("../shared/data/heads"))


def ants_anatomy(folder) -> Anatomy:
    """The ANTs 19.5-year head (six tissue probability maps c1..c6, grey matter .. air) as an Anatomy."""
    folder = Path(folder)
    maps, affine = [], None
    for c in (6, 1, 2, 3, 4, 5):  # air, GM, WM, CSF, skull, scalp
        a, affine = read_jnifti(folder / f"c{c}ANTS19-5Years_head.jnii")
        maps.append(a)
    fr = np.stack(maps)
    s = fr.sum(0)
    fr[0] += np.where(s < 1e-3, 1.0, 0.0)  # voxels with no tissue: air
    fr /= fr.sum(0, keepdims=True)
    return Anatomy(fr.astype(np.float32), affine, "ants19.5")


# ----------------------------------------------------------------------------------------------
# synthesis
# ----------------------------------------------------------------------------------------------


def _smooth_noise(shape, sigma_vox, rng) -> np.ndarray:
    """A smooth random field in [0, 1]."""
    f = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_vox, mode="wrap")
    f -= f.min()
    return f / max(f.max(), 1e-12)


def render(anatomy: Anatomy, modality: str, *, contrast: dict | None = None, noise: float = 0.0,
           bias: float = 0.0, texture: bool = True, seed: int = 0, psf_fwhm_mm: float = 0.0) -> Volume:
    """A synthetic MRI or CT of an anatomy: partial-volume tissue intensities, texture, blur, bias, noise.

    Arguments:
        anatomy: Anatomy.
        modality: "mri" (T1-like, white matter = 1) or "ct" (Hounsfield units).
        contrast: tissue intensities (keys of MRI_CONTRAST / CT_HU); missing ones take the defaults.
            "diploe" and "table" (CT) are used only where `anatomy.diploe` is given (`with_diploe`).
        noise: MRI: Rician noise sd as a fraction of white matter; CT: Gaussian noise sd in HU.
        bias: MRI only: peak |log| of a smooth multiplicative field (0.2 = up to +-20 %).
        texture: scalp as a smooth mixture of fat and muscle (else their mean).
        seed: random seed of texture, bias and noise.
        psf_fwhm_mm: the scanner's point-spread function beyond the voxel's own partial volume: a Gaussian
            of this full width at half maximum (mm, every axis) applied to the noiseless image, before the
            bias field and the noise (`blurred`; why, the comment above it). 0: none (each voxel is its box average alone, sharper
            than any scanner).
    Returns:
        Volume on the anatomy's grid.
    """
    if not (np.isfinite(psf_fwhm_mm) and psf_fwhm_mm >= 0):
        raise ValueError(f"render: `psf_fwhm_mm` must be a finite number >= 0 (mm; 0: no blur), got {psf_fwhm_mm!r}.")
    rng = np.random.default_rng(seed)
    base = dict(MRI_CONTRAST if modality == "mri" else CT_HU)
    base.update(contrast or {})
    vox = float(np.mean(voxel_sizes(anatomy.affine)))
    fat = _smooth_noise(anatomy.shape, 4.0 / vox, rng) if texture else 0.5
    scalp = base["fat"] * fat + base["muscle"] * (1 - fat)
    vals = [base["air"], base["grey_matter"], base["white_matter"], base["csf"], base["skull"], scalp]
    img = sum(f * v for f, v in zip(anatomy.fractions.astype(np.float64), vals))
    if anatomy.diploe is not None:  # that share of the skull is marrow, the rest compact table
        dip = anatomy.diploe.astype(np.float64)
        table = base.get("table", base["skull"])  # CT: compact bone; MRI: the skull's value is compact bone's
        img = img + dip * (base["diploe"] - base["skull"]) + (anatomy.fractions[4] - dip) * (table - base["skull"])
    if modality == "mri":
        if anatomy.t1 is not None and noise == 0 and bias == 0:
            # template: the measured T1 (scaled to white matter = the contrast's) where it is given
            wm = anatomy.fractions[2] > 0.9
            m = anatomy.t1 > 0
            if wm.any() and m.any():
                scale = base["white_matter"] / float(np.median(anatomy.t1[wm & m]))
                img = np.where(m, anatomy.t1 * scale, img)
    img = blurred(img, psf_fwhm_mm, voxel_sizes(anatomy.affine))
    if modality == "mri":
        if bias > 0:
            idx = np.meshgrid(*[np.linspace(-1, 1, n) for n in anatomy.shape], indexing="ij")
            c = rng.uniform(-1, 1, 9)
            field = sum(ci * t for ci, t in zip(c, [idx[0], idx[1], idx[2], idx[0] * idx[1], idx[1] * idx[2],
                                                      idx[0] * idx[2], idx[0] ** 2, idx[1] ** 2, idx[2] ** 2]))
            head = anatomy.fractions[0] < 0.5
            field -= field[head].mean()
            field *= bias / max(np.abs(field[head]).max(), 1e-12)
            img = img * np.exp(field)
    sd = noise * base["white_matter"] if modality == "mri" else noise
    return Volume(add_scanner_noise(img, sd, modality, rng), anatomy.affine)


# Why `render` can blur (`psf_fwhm_mm`). Its partial volume is each voxel's box average of the anatomy, the
# sharpest image a grid can hold. A scanner's is wider: an MRI's Fourier sampling alone gives a sinc of
# FWHM about 1.2 voxels along each axis (Haacke et al. 1999, "Magnetic Resonance Imaging: Physical Principles
# and Sequence Design"), more with T2 decay along the echo train or k-space filters; CT's
# reconstruction kernel sets its width. A box of one voxel (sd 0.29 voxel) and a Gaussian of FWHM 1 voxel
# (sd 0.42) together have an sd of 0.51 voxel (FWHM 1.2): about the sinc's.


def blurred(img: np.ndarray, fwhm_mm: float, voxel_mm) -> np.ndarray:
    """`img` convolved with an isotropic Gaussian of full width at half maximum `fwhm_mm` (mm), per axis in
    voxels of `voxel_mm` (3,) (sd = FWHM / (2 sqrt(2 ln 2))); edges continued by reflection. 0: `img` itself."""
    if fwhm_mm == 0:
        return img
    sd_vox = fwhm_mm / (2.0 * np.sqrt(2.0 * np.log(2.0))) / np.asarray(voxel_mm, np.float64)
    return ndimage.gaussian_filter(np.asarray(img, np.float64), sd_vox, mode="reflect")


def random_contrast(modality: str, rng: np.random.Generator) -> dict:
    """Tissue intensities drawn uniformly from MRI_CONTRAST_RANGE or CT_HU_RANGE."""
    ranges = MRI_CONTRAST_RANGE if modality == "mri" else CT_HU_RANGE
    return {k: float(rng.uniform(*r)) for k, r in ranges.items()}


#: The classes whose proportions `segment` learns from the scan where an anatomy does not model
#: bone (`Anatomy.unmodelled_bone`): the anatomy's soft tissue there is a placeholder that may be
#: bone. (Air in sinuses and airways is left to the background prior: in MRI bone and air are both
#: dark, and the anatomy says nothing about either.)
UNMODELLED_CLASSES = (Tissue.SKULL, Tissue.SCALP)


def unmodelled_map(anatomy: Anatomy, sigma_mm: float = 3.0) -> np.ndarray | None:
    """`anatomy.unmodelled_bone` blurred like the priors (`atlas_priors`), in [0, 1]; None without one."""
    if anatomy.unmodelled_bone is None:
        return None
    sig = sigma_mm / voxel_sizes(anatomy.affine)
    u = ndimage.gaussian_filter(anatomy.unmodelled_bone.astype(np.float64), sig, mode="nearest")
    return np.clip(u, 0.0, 1.0).astype(np.float32)


def atlas_priors(anatomy: Anatomy, *, sigma_mm: float = 3.0, spread: float = 0.05) -> np.ndarray:
    """(5, x, y, z) class priors from one anatomy: fractions blurred, plus a share of every head tissue.

    Arguments:
        anatomy: Anatomy (on the atlas grid).
        sigma_mm: Gaussian blur of the class fractions, mm: the spread of anatomy between people that
            one subject cannot show (the phantom atlas gets it from averaging; brain-surface
            variability after affine registration is several mm, e.g. Fonov et al. 2011).
        spread: inside the (blurred) head, this probability is shared equally among the four head
            classes, so that no tissue is impossible where the subject has it and the atlas has not
            (a thicker skull, a wider ventricle).
    Where `anatomy.unmodelled_bone` is set, the priors still say what the anatomy says (its
    placeholder soft tissue); `segment` learns the skull/scalp proportion there from the scan
    (`unmodelled_map`, `atlas.regional_proportions`).
    Returns:
        priors summing to 1 over classes.
    """
    cf = anatomy.class_fractions().astype(np.float64)
    sig = sigma_mm / voxel_sizes(anatomy.affine)
    p = np.stack([ndimage.gaussian_filter(c, sig, mode="nearest") for c in cf])
    head = 1.0 - p[0]
    p[1:] = (1 - spread) * p[1:] + spread * head[None] / 4.0
    p = np.clip(p, 0, None)
    return (p / p.sum(0, keepdims=True)).astype(np.float32)


def atlas_sources(anatomy: Anatomy, modality: str, voxel_mm: float, *, sigma_mm: float = 3.0,
                  spread: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Template, priors, affine and unmodelled-bone map (`unmodelled_map`, or None) of an atlas of one
    anatomy at `voxel_mm` (see `atlas_priors`).

    The template is `render` without noise or bias (MRI: the default T1 contrast, with the measured T1
    inside the brain where the anatomy carries one; CT: CT_HU), MRI scaled to brain median 1.
    """
    a = anatomy.resampled(voxel_mm)
    template = render(a, modality, texture=False).data
    if modality == "mri":
        brain = a.class_fractions()[int(Tissue.BRAIN)] > 0.5
        template = template / float(np.median(template[brain]))
    return template, atlas_priors(a, sigma_mm=sigma_mm, spread=spread), a.affine, unmodelled_map(a, sigma_mm)
