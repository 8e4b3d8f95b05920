"""Reading and writing volumes and label maps (NIfTI, Analyze); header info; resampling.  [host]

Images go through nibabel (NIfTI-1/2 ``.nii``/``.nii.gz`` and Analyze 7.5 / NIfTI-1 pairs
``.hdr``/``.img``), tetrahedral meshes through meshio (Gmsh ``.msh``, VTK ``.vtu``) and
scipy.io (MATLAB ``.mat``), surfaces through trimesh (``.stl``, ``.ply``, ``.obj``).

Every file is written atomically (:func:`atomic_write_path`): to a temporary file in the target
directory, renamed over the target only when the writer succeeded, so a crash or an exception
never leaves a half-written file under the final name.

Conventions: a volume's affine maps voxel *centres* (integer indices) to world mm, as NIfTI does
(NIfTI-1 header documentation, "qform/sform"), and loaded volumes are reoriented to the closest
canonical RAS+ orientation so that array axes run (roughly) Right, Anterior, Superior.
"""

from __future__ import annotations

import gzip
import logging
import os
import struct
import zlib
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
from nibabel.filebasedimages import ImageFileError
from nibabel.fileholders import FileHolder
from nibabel.spatialimages import HeaderDataError
from scipy import ndimage

from .._files import atomic_write_path
from ..tissue import Tissue
from ..volume import LabelMap, Volume, voxel_sizes

log = logging.getLogger(__name__)

#: Image formats read by load_volume/load_labels/info and written by save_volume/save_labels.
#: ``.hdr``/``.img`` are read as Analyze 7.5 or NIfTI-1 pairs and written as NIfTI-1 pairs.
VOLUME_EXTENSIONS: tuple[str, ...] = (".nii", ".nii.gz", ".hdr", ".img")

# Errors nibabel, gzip and numpy raise on damaged or foreign files.
_READ_ERRORS = (
    ImageFileError, HeaderDataError, OSError, EOFError, ValueError, zlib.error, struct.error,
    TypeError, KeyError, IndexError,
)


# Volumes: reading
# ---------------------------------------------------------------------------------------------


def _volume_kind(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz"):
        return "nii.gz"
    for ext in (".nii", ".hdr", ".img"):
        if name.endswith(ext):
            return ext[1:]
    raise ValueError(
        f"{str(path)!r}: unsupported image extension {''.join(path.suffixes) or '(none)'!r}; "
        f"supported: {', '.join(VOLUME_EXTENSIONS)} (convert other formats, e.g. DICOM with "
        "dcm2niix, to NIfTI first)."
    )


def _partner(path: Path, ext: str) -> Path:
    """The other file of an Analyze/NIfTI pair, with the case of the given suffix."""
    return path.with_suffix(ext.upper() if path.suffix.isupper() else ext)


def _check_readable(path: Path) -> str:
    kind = _volume_kind(path)
    if path.is_dir():
        raise ValueError(f"{str(path)!r} is a directory; pass an image file.")
    if not path.exists():
        raise FileNotFoundError(f"{str(path)!r}: no such file; check the path.")
    if kind in ("hdr", "img"):
        other = _partner(path, ".img" if kind == "hdr" else ".hdr")
        if not other.exists():
            raise FileNotFoundError(
                f"{str(path)!r} is half of an Analyze/NIfTI pair but its partner {str(other)!r} "
                "is missing; keep the .hdr and .img files together."
            )
    header_file = _partner(path, ".hdr") if kind == "img" else path
    if header_file.stat().st_size == 0:
        raise ValueError(f"{str(header_file)!r} is empty (0 bytes); re-export or re-download it.")
    return kind


def _header_problem(path: Path, kind: str) -> str:
    """Say why nibabel could not read the header of `path` (truncated, not gzip, not NIfTI)."""
    header_file = _partner(path, ".hdr") if kind == "img" else path
    head = b""
    try:
        if kind == "nii.gz":
            with open(header_file, "rb") as fh:
                magic = fh.read(2)
            if magic != b"\x1f\x8b":
                hint = ("it looks like an uncompressed NIfTI: rename it to .nii"
                        if _sizeof_hdr_ok(_read_head(header_file, gz=False)) else
                        "it is not an image file")
                return f"is named .gz but is not gzip-compressed ({hint})"
        head = _read_head(header_file, gz=kind == "nii.gz")
    except (EOFError, OSError, zlib.error) as e:
        return f"is truncated or corrupt: decompressing its header failed ({e})"
    if len(head) >= 4 and not _sizeof_hdr_ok(head):
        text = head[:40].decode("ascii", errors="replace")
        looks = (f"; it starts with text {text.splitlines()[0]!r}"
                 if text[:1].isprintable() and text.splitlines() else "")
        return ("is not a NIfTI/Analyze image: its first 4 bytes are not the header size "
                f"(sizeof_hdr 348 or 540){looks}")
    if len(head) < 348:
        return (f"is truncated: its header has {len(head)} bytes, but a NIfTI-1/Analyze header "
                "alone is 348 bytes")
    return ""


def _read_head(path: Path, gz: bool) -> bytes:
    opener = gzip.open if gz else open
    with opener(path, "rb") as fh:
        return fh.read(540)


def _sizeof_hdr_ok(head: bytes) -> bool:
    if len(head) < 4:
        return False
    return any(struct.unpack(e + "i", head[:4])[0] in (348, 540) for e in "<>")


def _open_image(path: str | os.PathLike) -> tuple[Any, Path]:
    """nibabel image of `path` (header read, data not yet) with file problems as ValueError."""
    path = Path(path)
    kind = _check_readable(path)
    try:
        img = nib.load(str(path))
    except _READ_ERRORS as e:
        problem = (_header_problem(path, kind)
                   or f"could not be read by nibabel ({' '.join(str(e).split())})")
        raise ValueError(
            f"{str(path)!r} {problem}. Check that it is a complete NIfTI or Analyze image; "
            "re-export or re-download it."
        ) from e
    return img, path


def _singular_affine(img) -> str | None:
    """Why an image's affine cannot place voxels in the world (None: it can)."""
    a = np.asarray(img.affine, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        return "contains NaN or Inf"
    det = np.linalg.det(a[:3, :3])
    if abs(det) < 1e-12:
        return f"is singular (det of its 3x3 part = {det:.3g}; voxel sizes {voxel_sizes(a).round(4).tolist()} mm)"
    return None


def _read_data(img, path: Path) -> np.ndarray:
    """All voxels as float64 with scl_slope/scl_inter applied; truncation as ValueError."""
    try:
        return np.asarray(img.get_fdata(dtype=np.float64))
    except _READ_ERRORS as e:
        hdr = img.header
        dtype = hdr.get_data_dtype()
        need = int(np.prod(img.shape)) * dtype.itemsize
        raise ValueError(
            f"{str(path)!r} is truncated or corrupt: reading its voxel data failed "
            f"({' '.join(str(e).split())}). The "
            f"header promises shape {tuple(img.shape)} of {dtype} ({need} bytes); re-export or "
            "re-download the file."
        ) from e


def _format_name(img) -> str:
    return {
        "Nifti1Image": "NIfTI-1", "Nifti2Image": "NIfTI-2", "Nifti1Pair": "NIfTI-1 pair",
        "Nifti2Pair": "NIfTI-2 pair", "AnalyzeImage": "Analyze 7.5",
        "Spm99AnalyzeImage": "Analyze 7.5 (SPM99)", "Spm2AnalyzeImage": "Analyze 7.5 (SPM2)",
    }.get(type(img).__name__, type(img).__name__)


def _load_3d(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, Path]:
    """Read, check and reorient one 3D image to canonical RAS: (data float64, affine, path)."""
    img, path = _open_image(path)
    shape = tuple(int(s) for s in img.shape)
    if 0 in shape:
        raise ValueError(
            f"{str(path)!r} has no voxels (shape {shape}); it is empty: re-export the image."
        )
    if len(shape) < 3 or min(shape[:3]) < 2:
        raise ValueError(
            f"{str(path)!r} is 2D (shape {shape}); jaxhead needs a 3D volume with at least 2 "
            "voxels along each axis: pass the full 3D scan, not a single slice."
        )
    if len(shape) > 3:
        n_vol = int(np.prod(shape[3:]))
        if n_vol > 1:
            raise ValueError(
                f"{str(path)!r} holds {n_vol} volumes (shape {shape}); jaxhead needs one 3D "
                "volume. Extract one first, e.g. `nibabel.load(path).slicer[..., 0]` then save, "
                "or `fslroi in out 0 1`."
            )
        log.info("%s: squeezed single-volume %dD image of shape %s to 3D", path, len(shape), shape)
        img = img.slicer[(slice(None),) * 3 + (0,) * (len(shape) - 3)]
    bad = _singular_affine(img)
    if bad:
        raise ValueError(
            f"{str(path)!r}: the header's voxel-to-world affine (sform/qform) {bad}, so voxels "
            "have no position in mm; fix the header (e.g. nibabel `img.set_sform(affine, 1)` or "
            "`fslorient`) and save the image again.")
    _warn_orientation(img, path)
    codes = "".join(nib.aff2axcodes(img.affine))
    img = nib.as_closest_canonical(img)
    if codes != "RAS":
        log.info("%s: reoriented from %s to canonical RAS", path, codes)
    data = _read_data(img, path)
    finite = np.isfinite(data)
    if not finite.all():
        n = int(data.size - finite.sum())
        first = tuple(int(i) for i in np.argwhere(~finite)[0])
        raise ValueError(
            f"{str(path)!r} has {n} of {data.size} voxels that are NaN or Inf (first at "
            f"canonical voxel {first}); replace them, e.g. `fslmaths in -nan out` or "
            "numpy.nan_to_num, and save the image again."
        )
    return data, np.asarray(img.affine, dtype=np.float64), path


def _warn_orientation(img, path: Path) -> None:
    """Report (never silently) images whose header carries no real orientation."""
    hdr = img.header
    if isinstance(img, (nib.Nifti1Image, nib.Nifti1Pair, nib.Nifti2Image, nib.Nifti2Pair)):
        if int(hdr["sform_code"]) == 0 and int(hdr["qform_code"]) == 0:
            log.warning(
                "%s: sform_code and qform_code are 0 (no orientation); nibabel's fallback affine "
                "(voxel sizes only, %s) is used", path, "".join(nib.aff2axcodes(img.affine)))
    elif isinstance(img, nib.AnalyzeImage):
        log.warning(
            "%s: Analyze 7.5 stores no orientation; nibabel assumes the radiological LAS "
            "convention (x flipped). Check left/right before trusting the result", path)


def load_volume(path: str | os.PathLike) -> Volume:
    """Read a 3D image, reoriented to canonical RAS, intensities scaled by scl_slope/scl_inter.

    A 4D file holding one volume is squeezed to 3D. Reorientation only permutes and flips the
    array (nibabel.as_closest_canonical); world coordinates of every voxel are unchanged.

    Arguments:
        path: ``.nii``, ``.nii.gz``, or an Analyze/NIfTI ``.hdr``/``.img`` pair (either name).

    Returns:
        Volume with data (x, y, z) float64 and affine (4, 4) voxel -> world mm.

    Raises:
        FileNotFoundError: the file (or the other half of a pair) does not exist.
        ValueError: unsupported extension; empty, 2D, multi-volume, truncated or non-image
            file; NaN/Inf voxels; an invalid affine. The message names the file.
    """
    data, affine, path = _load_3d(path)
    try:
        return Volume(data, affine)
    except ValueError as e:
        raise ValueError(f"{str(path)!r}: {e}") from e


def load_labels(path: str | os.PathLike) -> LabelMap:
    """Read a label image (integer Tissue values 0..4), reoriented to canonical RAS.

    Arguments:
        path: as for :func:`load_volume`.

    Returns:
        LabelMap with labels (x, y, z) uint8 and affine (4, 4) voxel -> world mm.
    """
    data, affine, path = _load_3d(path)
    rounded = np.round(data)
    if not np.array_equal(rounded, data):
        bad = np.unique(data[rounded != data])
        raise ValueError(
            f"{str(path)!r} is not a label image: it has non-integer values such as "
            f"{bad[:5].tolist()}; pass a label map with Tissue values "
            f"({', '.join(f'{t.value}={t.name}' for t in Tissue)}), or load it with load_volume."
        )
    try:
        return LabelMap(rounded.astype(np.int64), affine)
    except ValueError as e:
        raise ValueError(f"{str(path)!r}: {e}") from e


# ---------------------------------------------------------------------------------------------
# Volumes: writing
# ---------------------------------------------------------------------------------------------


def _write_image(data: np.ndarray, affine: np.ndarray, path: str | os.PathLike,
                 intent: str | None = None) -> Path:
    path = Path(path)
    kind = _volume_kind(path)
    pair = kind in ("hdr", "img")
    img = (nib.Nifti1Pair if pair else nib.Nifti1Image)(data, affine)
    hdr = img.header
    hdr.set_xyzt_units("mm")
    # Both codes 1 (scanner): the affine is the image's own world frame; readers prefer the
    # exact sform, the qform is its rigid approximation for tools that read only the qform.
    img.set_sform(affine, code="scanner")
    img.set_qform(affine, code="scanner")
    if intent is not None:
        hdr.set_intent(intent)
    if not pair:
        with atomic_write_path(path) as tmp:
            img.to_filename(str(tmp))
        return path
    # A NIfTI-1 pair (magic "ni1"): readable as Analyze by old tools, yet keeps the affine,
    # which plain Analyze 7.5 cannot store. Each file is written atomically, .img first.
    hdr_path, img_path = _partner(path, ".hdr"), _partner(path, ".img")
    with atomic_write_path(hdr_path) as th, atomic_write_path(img_path) as ti:
        img.to_file_map({"header": FileHolder(filename=str(th)),
                         "image": FileHolder(filename=str(ti))})
    return path


def save_volume(volume: Volume, path: str | os.PathLike, *, dtype: Any = np.float32) -> Path:
    """Write a Volume as NIfTI-1 (``.nii``, ``.nii.gz``, or a ``.hdr``/``.img`` pair), atomically.

    Arguments:
        volume: the image; its affine is stored as sform and qform (code 1, mm). NIfTI-1
            stores the sform in float32: affine entries round trip to ~1e-7 relative.
        path: target file; the extension picks the format.
        dtype: on-disk float type; float32 (default) keeps ~7 significant digits, which is
            below any scanner's noise; pass numpy.float64 for a bit-exact round trip.

    Returns:
        the path written.
    """
    if isinstance(volume, LabelMap):
        raise TypeError("save_volume got a LabelMap; use save_labels for label maps.")
    if not isinstance(volume, Volume):
        raise TypeError(f"save_volume needs a Volume, got {type(volume).__name__}.")
    dtype = np.dtype(dtype)
    if dtype.kind != "f":
        raise ValueError(f"`dtype` must be a float type (float32 or float64), got {dtype}.")
    data = volume.data.astype(dtype)
    if not np.all(np.isfinite(data)):
        raise ValueError(
            f"the volume's intensities overflow {dtype} (|max| = {np.abs(volume.data).max():.3g}); "
            "pass dtype=numpy.float64."
        )
    return _write_image(data, volume.affine, path)


def save_labels(labels: LabelMap, path: str | os.PathLike) -> Path:
    """Write a LabelMap as uint8 NIfTI with intent "label" (NIFTI_INTENT_LABEL), atomically.

    Arguments:
        labels: Tissue labels 0..4 (BACKGROUND, BRAIN, CSF, SKULL, SCALP).
        path: ``.nii``, ``.nii.gz`` or ``.hdr``/``.img``.

    Returns:
        the path written.
    """
    if not isinstance(labels, LabelMap):
        raise TypeError(
            f"save_labels needs a LabelMap, got {type(labels).__name__}"
            + ("; use save_volume for intensity images." if isinstance(labels, Volume) else ".")
        )
    return _write_image(labels.labels.astype(np.uint8), labels.affine, path, intent="label")


# ---------------------------------------------------------------------------------------------
# info
# ---------------------------------------------------------------------------------------------


def info(path: str | os.PathLike) -> dict[str, Any]:
    """Describe an image file as stored (before reorientation), for ``jaxhead info PATH``.

    Unlike load_volume this does not reject NaN/Inf, empty or multi-volume images: it reports
    them (``n_nonfinite``), so that a bad file can be inspected.

    Arguments:
        path: an image file (see VOLUME_EXTENSIONS).

    Returns:
        dict with keys path (str), format (str), shape (tuple), voxel_mm (3 floats),
        orientation (axis codes of the file's own affine, e.g. "LPS"), dtype (on-disk type),
        min, max, mean (of the finite scaled intensities; None if there are none),
        n_nonfinite (int) and affine (4x4 nested lists).
    """
    img, path = _open_image(path)
    hdr = img.header
    shape = tuple(int(s) for s in img.shape)
    data = _read_data(img, path)
    finite = data[np.isfinite(data)]
    stats = ((float(finite.min()), float(finite.max()), float(finite.mean()))
             if finite.size else (None, None, None))
    zooms = tuple(float(z) for z in hdr.get_zooms()[:3])
    bad = _singular_affine(img)
    if bad:
        orientation = f"none: the affine {bad}"
    else:
        orientation = "".join(nib.aff2axcodes(img.affine)) if len(shape) >= 3 else "n/a"
    return {
        "path": str(path),
        "format": _format_name(img),
        "shape": shape,
        "voxel_mm": zooms,
        "orientation": orientation,
        "dtype": str(hdr.get_data_dtype()),
        "min": stats[0],
        "max": stats[1],
        "mean": stats[2],
        "n_nonfinite": int(data.size - finite.size),
        "affine": np.asarray(img.affine, dtype=np.float64).tolist(),
    }


def format_info(d: dict[str, Any]) -> str:
    """Human-readable multi-line text of an :func:`info` dict."""

    def g(x):
        return "n/a" if x is None else f"{x:.6g}"

    lines = [
        ("file", d["path"]),
        ("format", d["format"]),
        ("shape", " x ".join(str(s) for s in d["shape"])),
        ("voxel size", " x ".join(f"{v:.4g}" for v in d["voxel_mm"]) + " mm"),
        ("orientation", d["orientation"] + ("" if d["orientation"] == "RAS"
                                              else " (load_volume reorients to RAS)")),
        ("data type", d["dtype"]),
        ("intensity", f"min {g(d['min'])}, max {g(d['max'])}, mean {g(d['mean'])}"),
    ]
    if d.get("n_nonfinite"):
        lines.append(("non-finite", f"{d['n_nonfinite']} voxels are NaN/Inf"))
    width = max(len(k) for k, _ in lines)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in lines)


# ---------------------------------------------------------------------------------------------
# Resampling
# ---------------------------------------------------------------------------------------------


def _antialias_sigma(factor: np.ndarray) -> np.ndarray:
    """Gaussian prefilter widths (in input voxels) for downsampling by `factor` per axis.

    A voxel of the coarser grid should report the mean over its footprint, i.e. the input
    convolved with a box f input voxels wide (partial-volume averaging, what a scanner with
    the coarser voxel measures). For an integer f that box average over f samples has variance
    (f^2 - 1) / 12 (a discrete uniform distribution); we use a Gaussian with that variance, so
    that for f = 1, 3, 5, ... the result reproduces f x f x f block averaging exactly on any
    quadratic and suppresses the Nyquist frequency of the input (e.g. f = 3: sigma = 0.82,
    gain 0.075 for scipy's sampled kernel, exp(-2 pi^2 sigma^2 / 4) = 0.037 for the continuous
    one; without the filter the Nyquist pattern aliases at full contrast).
    Up-sampling (f <= 1) needs no filter.
    scipy's sampled Gaussian has a variance within 0.1% of sigma^2 for sigma >= 0.8 (f >= 3);
    at f = 2 (sigma = 0.5) it is 14% below, a slightly milder filter.
    """
    f = np.maximum(np.asarray(factor, dtype=np.float64), 1.0)
    return np.sqrt((f**2 - 1.0) / 12.0)


def _parse_voxel_mm(voxel_mm) -> np.ndarray:
    try:
        v = np.broadcast_to(np.asarray(voxel_mm, dtype=np.float64), (3,)).copy()
    except (ValueError, TypeError):
        raise ValueError(
            f"`voxel_mm` must be one number or three (x, y, z), in mm; got {voxel_mm!r}."
        ) from None
    if not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise ValueError(f"`voxel_mm` must be positive and finite, got {v.tolist()} mm.")
    return v


def available_memory_bytes() -> int | None:
    """Memory this machine can still give a process (Linux MemAvailable; None if unknown)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"):
        if n < 1024 or unit == "EiB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"


def _check_memory(new_shape, old_vox, shape, new_vox) -> None:
    """Refuse up front a resample whose result would not fit in the machine's memory."""
    n = float(np.prod(new_shape.astype(np.float64)))
    # float64 result, plus the float64 copy and filtered input on the way: three arrays
    need = 8.0 * (n + 2 * float(np.prod(shape)))
    avail = available_memory_bytes()
    if avail is not None and need > avail:
        raise ValueError(
            f"resampling to `voxel_mm` = {new_vox.tolist()} would need about {_bytes(need)} "
            f"(shape {tuple(int(k) for k in new_shape)}) but {_bytes(avail)} are available; the "
            f"input's voxel size {old_vox.round(4).tolist()} mm (field of view "
            f"{(shape * old_vox).round(1).tolist()} mm) "
            + ("is implausible for a head: fix the header's voxel size"
               if np.any(old_vox > 50) else "is too fine for this machine")
            + ", or choose a larger `voxel_mm`.")


def resample(volume: Volume | LabelMap, voxel_mm, *, order: int | None = None) -> Volume | LabelMap:
    """Resample a Volume or LabelMap to a new voxel size over the same field of view.

    The field of view is the box covered by the voxels (centres +- half a voxel, as NIfTI
    places voxel centres at integer indices). The new grid has n' = round(n v / v') voxels per
    axis of size exactly v', centred on the same world point, so the box is kept up to v'/2
    in total (exactly when n v / v' is an integer). The new affine is A @ T with
    T: j -> s j + (n - 1)/2 - s (n' - 1)/2, s = v'/v, so world positions are preserved.

    Volumes use trilinear interpolation (order 1) by default; whatever the order, a Gaussian
    anti-aliasing filter is applied first along every axis that is downsampled (see
    _antialias_sigma). LabelMaps use nearest
    neighbour (order 0), the only order that keeps labels categorical; for even downsampling
    factors every output centre lies midway between input voxels and nearest neighbour breaks
    these ties the same way (scipy rounds up), moving boundaries by up to half an input voxel.
    Outside the input grid values are extended from the nearest edge voxel (at most half an
    input voxel).

    Arguments:
        volume: the Volume or LabelMap to resample.
        voxel_mm: new voxel size in mm, one number (isotropic) or three (per array axis).
        order: spline order 0..5 (scipy.ndimage) for a Volume, 0 for a LabelMap; None for
            the defaults (1 and 0).

    Returns:
        an object of the same type on the new grid.
    """
    if isinstance(volume, Volume):
        is_labels = False
        data = volume.data
    elif isinstance(volume, LabelMap):
        is_labels = True
        data = volume.labels
    else:
        raise TypeError(f"resample needs a Volume or a LabelMap, got {type(volume).__name__}.")
    new_vox = _parse_voxel_mm(voxel_mm)
    if order is None:
        order = 0 if is_labels else 1
    if not isinstance(order, (int, np.integer)) or isinstance(order, bool) or not 0 <= order <= 5:
        raise ValueError(f"`order` must be an integer 0..5 (spline order) or None, got {order!r}.")
    if is_labels and order != 0:
        raise ValueError(
            f"`order` = {order} on a LabelMap would mix tissue numbers; labels are resampled by "
            "nearest neighbour (order=0). For smoother label maps resample each tissue's "
            "indicator as a Volume and take the arg-max."
        )
    old_vox = voxel_sizes(volume.affine)
    shape = np.asarray(data.shape, dtype=np.float64)
    new_shape = np.floor(shape * old_vox / new_vox + 0.5).astype(int)
    if np.any(new_shape < 2):
        raise ValueError(
            f"`voxel_mm` = {new_vox.tolist()} is too coarse for a field of view of "
            f"{(shape * old_vox).round(2).tolist()} mm: the result would have shape "
            f"{tuple(new_shape.tolist())}; every axis needs >= 2 voxels."
        )
    _check_memory(new_shape, old_vox, shape, new_vox)
    scale = new_vox / old_vox  # input voxels per output voxel, per axis
    offset = (shape - 1) / 2 - scale * (new_shape - 1) / 2
    t = np.eye(4)
    t[:3, :3] = np.diag(scale)
    t[:3, 3] = offset
    affine = volume.affine @ t
    sigma = _antialias_sigma(scale)
    out_shape = tuple(int(n) for n in new_shape)

    def warp(x: np.ndarray) -> np.ndarray:
        # A diagonal matrix makes affine_transform take scipy's fast zoom/shift path; output
        # voxel j samples input voxel coordinate scale * j + offset.
        return ndimage.affine_transform(x, scale, offset=offset, output_shape=out_shape,
                                        order=order, mode="nearest")

    if is_labels:
        return LabelMap(warp(data), affine)
    if np.any(sigma > 0):
        data = ndimage.gaussian_filter(data, sigma, mode="nearest")
    return Volume(warp(data), affine)


