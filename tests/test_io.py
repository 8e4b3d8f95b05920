"""Tests of jaxhead.io: round trips, bad input, resampling, mesh/surface exports, atomic writes."""

import gzip
import logging
import os
import struct

import meshio
import nibabel as nib
import numpy as np
import pytest
import scipy.io
import trimesh
from scipy.spatial import Delaunay

from jaxhead.io import (
    atomic_write_path,
    format_info,
    info,
    load_labels,
    load_mesh,
    load_surface,
    load_volume,
    resample,
    save_labels,
    save_mesh,
    save_surface,
    save_volume,
)
from jaxhead.geometry import TetMesh, orient_tets, signed_volumes
from jaxhead.geometry.surface import Surface
from jaxhead.tissue import Tissue
from jaxhead.volume import LabelMap, Volume, default_affine

# float32 on disk: relative rounding 2^-24 ~ 6e-8 (IEEE 754 binary32).
F32_RTOL = 1e-7


def _affine(codes: str, voxel=(1.0, 1.5, 2.0), origin=(10.0, -20.0, 30.0)) -> np.ndarray:
    """An affine whose array axes point along the given axis codes (e.g. "LPS", "LIA")."""
    axis = {"R": (0, 1), "L": (0, -1), "A": (1, 1), "P": (1, -1), "S": (2, 1), "I": (2, -1)}
    a = np.zeros((4, 4))
    for j, c in enumerate(codes):
        row, sign = axis[c]
        a[row, j] = sign * voxel[j]
    a[:3, 3] = origin
    a[3, 3] = 1.0
    return a


def _write_nifti(path, data, affine=None):
    img = nib.Nifti1Image(np.asarray(data), np.eye(4) if affine is None else affine)
    img.set_sform(img.affine, code=1)
    img.set_qform(img.affine, code=1)
    img.to_filename(str(path))
    return path


def _volume(shape=(9, 10, 11), seed=0, affine=None) -> Volume:
    rng = np.random.default_rng(seed)
    return Volume(rng.normal(100.0, 20.0, shape),
                  default_affine((1.0, 1.25, 1.5), shape) if affine is None else affine)


# ------------------------------------------------------------------------------ atomic writes


def test_atomic_write_path_renames_on_success_and_keeps_suffix(tmp_path):
    target = tmp_path / "head.nii.gz"
    with atomic_write_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.endswith(".nii.gz") and tmp != target
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new"
    assert os.listdir(tmp_path) == ["head.nii.gz"]


def test_atomic_write_path_does_not_clobber_on_failure(tmp_path):
    target = tmp_path / "mesh.vtu"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="writer broke"):
        with atomic_write_path(target) as tmp:
            tmp.write_bytes(b"half-writ")
            raise RuntimeError("writer broke")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["mesh.vtu"]


def test_atomic_write_path_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="did not create"):
        with atomic_write_path(tmp_path / "x.stl"):
            pass
    with pytest.raises(FileNotFoundError, match="does not exist"):
        with atomic_write_path(tmp_path / "nodir" / "x.stl"):
            pass
    assert os.listdir(tmp_path) == []


def test_savers_leave_no_temp_files(tmp_path, small_mesh):
    save_volume(_volume(), tmp_path / "a.nii.gz")
    save_volume(_volume(), tmp_path / "a.nii.gz")  # overwrite
    save_labels(_labelmap(), tmp_path / "b.hdr")
    save_mesh(small_mesh, tmp_path / "m.msh")
    assert sorted(os.listdir(tmp_path)) == ["a.nii.gz", "b.hdr", "b.img", "m.msh"]


# ------------------------------------------------------------------------------ volume round trips


@pytest.mark.parametrize("name", ["v.nii", "v.nii.gz", "v.hdr", "v.img"])
def test_volume_round_trip(tmp_path, name):
    # Oblique but closest to RAS, so loading keeps the array layout (reorientation is
    # tested below).
    c, s = np.cos(0.3), np.sin(0.3)
    aff = np.diag([1.0, 1.25, 0.8, 1.0])
    aff[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ aff[:3, :3]
    aff[:3, 3] = [-4.0, 6.5, 2.0]
    vol = _volume(affine=aff)
    save_volume(vol, tmp_path / name)
    back = load_volume(tmp_path / name)
    np.testing.assert_allclose(back.data, vol.data, rtol=F32_RTOL)
    # NIfTI-1 stores the sform in float32: entries up to ~7 mm, 7 * 2^-24 ~ 4e-7 mm.
    np.testing.assert_allclose(back.affine, vol.affine, rtol=0, atol=1e-6)
    exact = tmp_path / ("x" + name[1:])
    save_volume(vol, exact, dtype=np.float64)
    np.testing.assert_array_equal(load_volume(exact).data, vol.data)


@pytest.mark.parametrize("codes", ["LPS", "LIA", "PSR"])
def test_load_reorients_to_ras_with_same_world_coordinates(tmp_path, codes):
    rng = np.random.default_rng(1)
    data = rng.normal(size=(6, 7, 8)).astype(np.float32)
    aff = _affine(codes)
    path = _write_nifti(tmp_path / "o.nii.gz", data, aff)
    vol = load_volume(path)
    assert nib.aff2axcodes(vol.affine) == ("R", "A", "S")
    assert np.all(np.diag(vol.affine)[:3] > 0)
    assert info(path)["orientation"] == codes
    # Every loaded voxel holds the original value of the voxel at the same world point.
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in vol.shape], indexing="ij"), -1).reshape(-1, 3)
    world = idx @ vol.affine[:3, :3].T + vol.affine[:3, 3]
    orig = np.linalg.solve(aff[:3, :3], (world - aff[:3, 3]).T).T
    orig_idx = np.round(orig).astype(int)
    np.testing.assert_allclose(orig, orig_idx, atol=1e-9)
    np.testing.assert_array_equal(vol.data[tuple(idx.T)], data[tuple(orig_idx.T)])


def test_load_applies_scl_slope_and_inter(tmp_path):
    raw = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)
    path = _write_nifti(tmp_path / "s.nii", raw)
    b = bytearray(path.read_bytes())
    b[112:120] = struct.pack("<ff", 2.0, -10.0)  # NIfTI-1 header: scl_slope @112, scl_inter @116
    path.write_bytes(bytes(b))
    np.testing.assert_array_equal(load_volume(path).data, 2.0 * raw - 10.0)


def test_plain_analyze_is_read_and_orientation_assumption_reported(tmp_path, caplog):
    data = np.arange(3 * 4 * 5, dtype=np.int16).reshape(3, 4, 5)
    nib.AnalyzeImage(data, np.diag([2.0, 2.0, 2.0, 1.0])).to_filename(str(tmp_path / "an.hdr"))
    with caplog.at_level(logging.WARNING, logger="jaxhead.io"):
        vol = load_volume(tmp_path / "an.img")
    assert "no orientation" in caplog.text
    # nibabel reads Analyze as LAS (x flipped); canonical RAS flips x back.
    np.testing.assert_array_equal(vol.data, data[::-1].astype(np.float64))
    assert info(tmp_path / "an.hdr")["orientation"] == "LAS"


def test_missing_orientation_is_reported(tmp_path, caplog):
    img = nib.Nifti1Image(np.ones((3, 4, 5), np.float32), np.eye(4))
    img.set_sform(None, code=0)
    img.set_qform(None, code=0)
    img.to_filename(str(tmp_path / "bare.nii"))
    with caplog.at_level(logging.WARNING, logger="jaxhead.io"):
        load_volume(tmp_path / "bare.nii")
    assert "no orientation" in caplog.text


def test_4d_single_volume_squeezed_multi_rejected(tmp_path):
    data = np.random.default_rng(2).normal(size=(5, 6, 7)).astype(np.float32)
    p1 = _write_nifti(tmp_path / "one.nii", data[..., None], _affine("RAS"))
    np.testing.assert_array_equal(load_volume(p1).data, data)
    p3 = _write_nifti(tmp_path / "three.nii", np.stack([data] * 3, -1), _affine("RAS"))
    with pytest.raises(ValueError, match=r"three\.nii.*3 volumes.*slicer"):
        load_volume(p3)


def test_labels_round_trip_uint8_label_intent(tmp_path):
    lab = _labelmap()
    path = save_labels(lab, tmp_path / "seg.nii.gz")
    img = nib.load(str(path))
    assert img.get_data_dtype() == np.uint8
    assert img.header.get_intent()[0] == "label"
    back = load_labels(path)
    np.testing.assert_array_equal(back.labels, lab.labels)
    np.testing.assert_allclose(back.affine, lab.affine, atol=1e-12)


def test_load_labels_rejects_non_labels(tmp_path):
    p = _write_nifti(tmp_path / "f.nii", np.full((3, 3, 3), 1.5, np.float32))
    with pytest.raises(ValueError, match=r"f\.nii.*non-integer"):
        load_labels(p)
    p = _write_nifti(tmp_path / "g.nii", np.full((3, 3, 3), 7, np.uint8))
    with pytest.raises(ValueError, match=r"g\.nii.*outside 0\.\.4"):
        load_labels(p)


def test_save_rejects_wrong_types(tmp_path):
    with pytest.raises(TypeError, match="save_labels"):
        save_volume(_labelmap(), tmp_path / "x.nii")
    with pytest.raises(TypeError, match="save_volume"):
        save_labels(_volume(), tmp_path / "x.nii")
    with pytest.raises(ValueError, match="unsupported image extension '.png'.*\\.nii\\.gz"):
        save_volume(_volume(), tmp_path / "x.png")


# ------------------------------------------------------------------------------ bad image input


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_voxels_rejected(tmp_path, bad):
    data = np.ones((4, 4, 4), np.float32)
    data[1, 2, 3] = bad
    p = _write_nifti(tmp_path / "n.nii.gz", data)
    with pytest.raises(ValueError, match=r"n\.nii\.gz.*1 of 64 voxels.*NaN or Inf.*nan_to_num"):
        load_volume(p)
    assert info(p)["n_nonfinite"] == 1  # info reports instead of refusing


def test_empty_image_rejected(tmp_path):
    p = _write_nifti(tmp_path / "e.nii", np.zeros((0, 4, 4), np.float32))
    with pytest.raises(ValueError, match=r"e\.nii.*no voxels"):
        load_volume(p)
    z = tmp_path / "zero.nii"
    z.write_bytes(b"")
    with pytest.raises(ValueError, match=r"zero\.nii.*empty \(0 bytes\)"):
        load_volume(z)


@pytest.mark.parametrize("shape", [(8, 9), (8, 9, 1)])
def test_2d_image_rejected(tmp_path, shape):
    p = _write_nifti(tmp_path / "flat.nii", np.ones(shape, np.float32))
    with pytest.raises(ValueError, match=r"flat\.nii.*is 2D.*3D volume"):
        load_volume(p)


@pytest.mark.parametrize("name", ["t.nii", "t.nii.gz"])
@pytest.mark.parametrize("keep", [0.05, 0.5, 0.97])
def test_truncated_file_rejected(tmp_path, name, keep):
    full = tmp_path / ("full_" + name)
    _write_nifti(full, np.random.default_rng(3).normal(size=(10, 10, 10)).astype(np.float32))
    blob = full.read_bytes()
    cut = tmp_path / name
    cut.write_bytes(blob[: int(len(blob) * keep)])
    with pytest.raises(ValueError, match=rf"{name.replace('.', '[.]')}.*truncated"):
        load_volume(cut)


def test_text_file_named_nifti_rejected(tmp_path):
    p = tmp_path / "notes.nii"
    p.write_text("these are my notes about subject 1\n" * 20)  # longer than a header
    with pytest.raises(ValueError, match=r"notes\.nii.*not a NIfTI/Analyze image.*these are my"):
        load_volume(p)
    (tmp_path / "short.nii").write_text("hello\n")
    with pytest.raises(ValueError, match=r"short\.nii.*not a NIfTI/Analyze image"):
        load_volume(tmp_path / "short.nii")
    g = tmp_path / "notes.nii.gz"
    g.write_text("hello\n" * 100)
    with pytest.raises(ValueError, match=r"notes\.nii\.gz.*not gzip-compressed"):
        load_volume(g)


def test_uncompressed_nifti_named_gz_gets_rename_hint(tmp_path):
    p = _write_nifti(tmp_path / "plain.nii", np.ones((3, 3, 3), np.float32))
    g = tmp_path / "plain.nii.gz"
    g.write_bytes(p.read_bytes())
    with pytest.raises(ValueError, match="rename it to .nii"):
        load_volume(g)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.nii"):
        load_volume(tmp_path / "nothere.nii")
    with pytest.raises(ValueError, match=r"scan\.dcm.*unsupported.*\.nii, \.nii\.gz, \.hdr, \.img"):
        load_volume(tmp_path / "scan.dcm")
    nib.Nifti1Pair(np.ones((3, 3, 3), np.float32), np.eye(4)).to_filename(str(tmp_path / "p.hdr"))
    (tmp_path / "p.hdr").unlink()
    with pytest.raises(FileNotFoundError, match=r"p\.hdr.*missing"):
        load_volume(tmp_path / "p.img")


def test_truncated_gzip_header(tmp_path):
    g = tmp_path / "h.nii.gz"
    with gzip.open(g, "wb") as fh:
        fh.write(struct.pack("<i", 348) + b"\0" * 100)
    with pytest.raises(ValueError, match=r"h\.nii\.gz.*truncated"):
        load_volume(g)


# ------------------------------------------------------------------------------ info


def test_info_and_format_info(tmp_path):
    data = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)
    p = _write_nifti(tmp_path / "i.nii.gz", data, _affine("LPS", voxel=(0.5, 0.5, 1.2)))
    d = info(p)
    assert d["shape"] == (4, 5, 6)
    np.testing.assert_allclose(d["voxel_mm"], (0.5, 0.5, 1.2), rtol=F32_RTOL)
    assert d["orientation"] == "LPS" and d["dtype"] == "int16" and d["format"] == "NIfTI-1"
    assert (d["min"], d["max"], d["mean"]) == (0.0, 119.0, 59.5)
    text = format_info(d)
    assert "LPS" in text and "4 x 5 x 6" in text and "int16" in text and "max 119" in text


# ------------------------------------------------------------------------------ resampling


def _world_grid(affine, shape):
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    return idx @ affine[:3, :3].T + affine[:3, 3]


def _rotated_affine(voxel, shape):
    """An oblique, axis-permuted affine (tests must not assume a diagonal one)."""
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[0, 0, 1], [-1, 0, 0], [0, 1, 0]])
    a = np.eye(4)
    a[:3, :3] = rot * np.asarray(voxel)
    a[:3, 3] = [5.0, -7.0, 3.0]
    return a


@pytest.mark.parametrize("new_vox", [0.7, 2.1, (1.3, 0.6, 2.5)])
def test_resample_linear_function_is_exact(new_vox):
    shape = (24, 20, 22)
    aff = _rotated_affine((1.0, 1.2, 0.9), shape)
    coef, c0 = np.array([0.3, -1.1, 0.7]), 4.0
    vol = Volume(_world_grid(aff, shape) @ coef + c0, aff)
    out = resample(vol, new_vox)
    np.testing.assert_allclose(out.voxel_mm, np.broadcast_to(new_vox, (3,)), rtol=1e-12)
    expected = _world_grid(out.affine, out.shape) @ coef + c0
    # Trilinear interpolation and the symmetric Gaussian prefilter reproduce linear functions
    # exactly away from the edges, where edge extension (mode "nearest") and the filter's
    # support reach outside the grid: here f <= 2.8, sigma <= 0.77, kernel radius
    # int(4 sigma + 0.5) = 3 voxels, +1 for the interpolation stencil, +1 to spare.
    src = (np.linalg.inv(aff) @ np.c_[_world_grid(out.affine, out.shape).reshape(-1, 3),
                                        np.ones(out.data.size)].T)[:3].T
    margin = 5
    inside = np.all((src >= margin) & (src <= np.array(shape) - 1 - margin), axis=1)
    assert inside.sum() > 50
    # float64 rounding of O(10) values through a few hundred operations: 1e-10 absolute.
    np.testing.assert_allclose(out.data.reshape(-1)[inside], expected.reshape(-1)[inside], atol=1e-10)


def test_resample_preserves_field_of_view_and_round_trips():
    vol = _volume((20, 22, 24), affine=_rotated_affine((1.0, 1.0, 1.0), (20, 22, 24)))
    down = resample(vol, 2.0)
    assert down.shape == (10, 11, 12)
    # The field of view's corners (outer voxel edges) map to the same world points.
    def corners(v):
        n = np.array(v.shape)
        c = np.array([[-0.5 if b == "0" else m - 0.5 for b, m in zip(f"{k:03b}", n)] for k in range(8)])
        return c @ v.affine[:3, :3].T + v.affine[:3, 3]
    np.testing.assert_allclose(corners(down), corners(vol), atol=1e-12)
    up = resample(down, 1.0)
    assert up.shape == vol.shape
    np.testing.assert_allclose(up.affine, vol.affine, atol=1e-12)


def test_resample_preserves_feature_positions():
    shape = (40, 36, 44)
    aff = _rotated_affine((1.0, 1.0, 1.0), shape)
    world = _world_grid(aff, shape)
    centre = world[17, 20, 23] + np.array([0.3, -0.2, 0.4])
    blob = np.exp(-((world - centre) ** 2).sum(-1) / (2 * 3.0**2))
    for new_vox in (0.8, 1.7, 2.5):
        out = resample(Volume(blob, aff), new_vox)
        w = _world_grid(out.affine, out.shape)
        com = (out.data[..., None] * w).sum((0, 1, 2)) / out.data.sum()
        # A 3 mm Gaussian sampled at <= 2.5 mm: the discrete centre of mass is exact up to
        # aliasing of order exp(-2 pi^2 sigma^2 / h^2) ~ 1e-12; interpolation error is
        # symmetric about the centre. 0.02 mm leaves room for the grid's asymmetry at the edges.
        np.testing.assert_allclose(com, centre, atol=0.02)
    lab = LabelMap((((world - centre) ** 2).sum(-1) < 11.0**2).astype(np.uint8), aff)
    # Factors without systematic ties (at factor 2 every output centre falls midway between
    # input voxels and nearest neighbour breaks all ties the same way: the documented
    # half-voxel shift).
    for new_vox in (0.8, 1.7, 2.6):
        out = resample(lab, new_vox)
        assert out.labels.dtype == np.uint8 and set(np.unique(out.labels)) <= {0, 1}
        w = _world_grid(out.affine, out.shape)[out.labels == 1]
        # Centroid of a voxelised 11 mm ball: boundary voxels flip at irregular positions
        # (measured error <= 0.15 mm); a wrong voxel-centre convention would shift it by
        # (h' - h) / 2 per axis (0.8 mm at 2.6 mm).
        np.testing.assert_allclose(w.mean(0), centre, atol=0.25)


def test_resample_downsampling_matches_block_average_and_suppresses_aliasing():
    shape = (30, 33, 27)
    vol_aff = default_affine(1.0, shape)
    i, j, k = np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij")
    quad = 0.02 * i**2 - 0.03 * j * k + 0.01 * k**2 + i
    out = resample(Volume(quad, vol_aff), 3.0)
    blocks = quad.reshape(10, 3, 11, 3, 9, 3).mean((1, 3, 5))
    # f = 3: the Gaussian has the block's variance 2/3 per axis, so quadratics agree exactly
    # except for the sampled kernel's variance error (< 1e-3 relative) times the curvature
    # (|d2/dx2| <= 0.04): < 1e-4. Edges (filter reach 4 voxels) excluded.
    np.testing.assert_allclose(out.data[2:-2, 2:-2, 2:-2], blocks[2:-2, 2:-2, 2:-2], atol=1e-4)
    alt = np.where(np.arange(shape[0]) % 2 == 0, 1.0, -1.0)[:, None, None] * np.ones(shape)
    down = resample(Volume(alt, vol_aff), 3.0)
    # Output samples sit on input voxels 3j+1, so without a prefilter they would read +-1
    # (full-contrast aliasing). The sampled Gaussian (sigma^2 = 2/3, radius 3) has gain
    # (1 - 2 e^-0.75 + 2 e^-3 - 2 e^-6.75) / (1 + 2 e^-0.75 + 2 e^-3 + 2 e^-6.75) = 0.0745 there
    # (the continuous one: exp(-2 pi^2 (2/3) / 4) = 0.037).
    np.testing.assert_allclose(np.abs(down.data[2:-2]), 0.0745, atol=1e-3)


def test_resample_labels_nearest_neighbour():
    shape = (16, 16, 16)
    labels = np.zeros(shape, np.uint8)
    labels[3:13, 3:13, 3:13] = 4
    labels[5:11, 5:11, 5:11] = 1
    lm = LabelMap(labels, default_affine(1.0, shape))
    up = resample(lm, 0.5)
    assert up.shape == (32, 32, 32)
    # Upsampling by 2 with nearest neighbour replicates each voxel into a 2x2x2 block.
    np.testing.assert_array_equal(up.labels, labels.repeat(2, 0).repeat(2, 1).repeat(2, 2))
    # Downsampling by 3 picks the centre voxel of each 3x3x3 block.
    np.testing.assert_array_equal(resample(LabelMap(labels[:15, :15, :15], lm.affine), 3.0).labels,
                                  labels[1:15:3, 1:15:3, 1:15:3])
    with pytest.raises(ValueError, match="nearest neighbour"):
        resample(lm, 2.0, order=1)


def test_resample_labels_keeps_tissue_volumes():
    shape = (30, 30, 30)
    aff = default_affine(1.0, shape)
    r = np.linalg.norm(_world_grid(aff, shape) - [0.3, -0.4, 0.2], axis=-1)
    labels = np.select([r < 6.0, r < 8.0, r < 10.0, r < 12.0], [1, 2, 3, 4], 0).astype(np.uint8)
    lm = LabelMap(labels, aff)
    exact = np.diff(4 / 3 * np.pi * np.array([0.0, 6.0, 8.0, 10.0, 12.0]) ** 3)
    for new_vox in (0.7, 1.3, 2.0):
        vols = resample(lm, new_vox).tissue_volumes_mm3()
        got = np.array([vols[t] for t in (Tissue.BRAIN, Tissue.CSF, Tissue.SKULL, Tissue.SCALP)])
        # Voxelising 2 mm thick shells on a 0.7-2 mm grid: boundary voxels flip either way;
        # measured <= 11% for the thin shells at 1.3 mm (and 2% for the input at 1 mm), 15%
        # bounds it.
        np.testing.assert_allclose(got, exact, rtol=0.15)


def test_resample_rejects_bad_arguments():
    vol = _volume()
    with pytest.raises(ValueError, match="`voxel_mm` must be positive"):
        resample(vol, -1.0)
    with pytest.raises(ValueError, match="`voxel_mm` must be one number or three"):
        resample(vol, (1.0, 2.0))
    with pytest.raises(ValueError, match="too coarse"):
        resample(vol, 50.0)
    with pytest.raises(ValueError, match="`order` must be an integer 0..5"):
        resample(vol, 1.0, order=7)
    with pytest.raises(TypeError, match="Volume or a LabelMap"):
        resample(np.zeros((3, 3, 3)), 1.0)


# ------------------------------------------------------------------------------ meshes


def _labelmap():
    shape = (8, 9, 10)
    lab = np.zeros(shape, np.uint8)
    lab[1:7, 1:8, 1:9] = 4
    lab[2:6, 2:7, 2:8] = 3
    lab[3:5, 3:6, 3:7] = 1
    return LabelMap(lab, default_affine(1.5, shape))


@pytest.fixture
def small_mesh() -> TetMesh:
    rng = np.random.default_rng(4)
    pts = np.concatenate([rng.uniform(-10, 10, (40, 3)),
                          np.array(np.meshgrid([-10, 10], [-10, 10], [-10, 10])).reshape(3, -1).T])
    tets, _ = orient_tets(pts, Delaunay(pts).simplices)
    tets = tets[signed_volumes(pts, tets) > 1e-6]
    r = np.linalg.norm(pts[tets].mean(1), axis=1)
    labels = 1 + np.searchsorted(np.quantile(r, [0.25, 0.5, 0.75]), r)
    mesh = TetMesh(pts, tets, labels)
    assert set(np.unique(mesh.labels)) == {1, 2, 3, 4}
    return mesh


@pytest.mark.parametrize("name,binary", [("m.msh", True), ("m.msh", False), ("m.vtu", True),
                                         ("m.vtu", False), ("m.mat", True)])
def test_mesh_round_trip(tmp_path, small_mesh, name, binary):
    save_mesh(small_mesh, tmp_path / name, binary=binary)
    back = load_mesh(tmp_path / name)
    # Binary formats store float64 exactly; meshio's ASCII VTU writer prints 11 decimals
    # (|x| <= 10 mm here: 5e-11 mm), its ASCII Gmsh writer 16 significant digits.
    np.testing.assert_allclose(back.nodes, small_mesh.nodes, rtol=0, atol=0 if binary else 1e-10)
    np.testing.assert_array_equal(back.tets, small_mesh.tets)
    np.testing.assert_array_equal(back.labels, small_mesh.labels)
    assert np.all(back.tet_volumes() > 0)


def test_msh_has_named_physical_groups(tmp_path, small_mesh):
    save_mesh(small_mesh, tmp_path / "g.msh", binary=False)
    text = (tmp_path / "g.msh").read_text()
    assert text.startswith("$MeshFormat\n2.2")
    for t in ("BRAIN", "CSF", "SKULL", "SCALP"):
        assert f'3 {int(Tissue[t])} "{t}"' in text
    m = meshio.read(tmp_path / "g.msh")
    np.testing.assert_array_equal(m.cell_data_dict["gmsh:geometrical"]["tetra"], small_mesh.labels)


def test_msh_tags_mapped_through_tissue_names(tmp_path, small_mesh):
    tags = small_mesh.labels * 10  # another tool's numbering: 10, 20, 30, 40
    m = meshio.Mesh(small_mesh.nodes, [("tetra", small_mesh.tets)],
                    cell_data={"gmsh:physical": [tags], "gmsh:geometrical": [tags]},
                    field_data={"brain": np.array([10, 3]), "csf": np.array([20, 3]),
                                "Skull": np.array([30, 3]), "scalp": np.array([40, 3])})
    meshio.write(tmp_path / "other.msh", m, file_format="gmsh22")
    np.testing.assert_array_equal(load_mesh(tmp_path / "other.msh").labels, small_mesh.labels)


def test_mat_layout_is_matlab_style(tmp_path, small_mesh):
    save_mesh(small_mesh, tmp_path / "m.mat")
    d = scipy.io.loadmat(tmp_path / "m.mat")
    assert d["node"].shape == (small_mesh.n_nodes, 3)
    assert d["element"].shape == (small_mesh.n_tets, 4) and d["element"].min() == 1
    assert d["element"].max() == small_mesh.n_nodes
    assert d["tissue"].shape == (small_mesh.n_tets, 1)
    np.testing.assert_array_equal(d["element"] - 1, small_mesh.tets)


def test_load_mesh_orientation_is_checked_not_repaired(tmp_path, small_mesh):
    flipped = small_mesh.tets[:, [0, 2, 1, 3]]
    meshio.write(tmp_path / "neg.vtu", meshio.Mesh(small_mesh.nodes, [("tetra", flipped)],
                                                    cell_data={"tissue": [small_mesh.labels]}))
    with pytest.raises(ValueError, match=r"neg\.vtu.*negatively oriented.*reorient=True"):
        load_mesh(tmp_path / "neg.vtu")
    fixed = load_mesh(tmp_path / "neg.vtu", reorient=True)
    np.testing.assert_allclose(fixed.tet_volumes(), small_mesh.tet_volumes(), rtol=1e-12)


def test_mesh_bad_input(tmp_path, small_mesh):
    with pytest.raises(ValueError, match=r"unsupported mesh extension '\.unv'.*\.msh, \.vtu, \.mat"):
        save_mesh(small_mesh, tmp_path / "m.unv")
    with pytest.raises(ValueError, match="unsupported mesh extension"):
        load_mesh(tmp_path / "m.off")
    with pytest.raises(FileNotFoundError, match="gone.msh"):
        load_mesh(tmp_path / "gone.msh")
    (tmp_path / "junk.msh").write_text("not a mesh\n")
    with pytest.raises(ValueError, match=r"junk\.msh.*could not be read"):
        load_mesh(tmp_path / "junk.msh")
    meshio.write(tmp_path / "nolab.vtu", meshio.Mesh(small_mesh.nodes, [("tetra", small_mesh.tets)]))
    with pytest.raises(ValueError, match=r"nolab\.vtu.*no cell data 'tissue'"):
        load_mesh(tmp_path / "nolab.vtu")
    scipy.io.savemat(tmp_path / "zero.mat", {"node": small_mesh.nodes, "element": small_mesh.tets,
                                             "tissue": small_mesh.labels})
    with pytest.raises(ValueError, match=r"zero\.mat.*1-based"):
        load_mesh(tmp_path / "zero.mat")


# ------------------------------------------------------------------------------ surfaces


@pytest.mark.parametrize("ext", [".stl", ".ply", ".obj"])
def test_surface_round_trip(tmp_path, ext):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=80.0)
    surf = Surface(sphere.vertices + [1.0, -2.0, 3.0], sphere.faces, Tissue.SCALP)
    save_surface(surf, tmp_path / ("s" + ext))
    back = load_surface(tmp_path / ("s" + ext), "scalp")
    assert back.tissue == Tissue.SCALP and back.faces.shape == surf.faces.shape
    # Triangles as coordinate triples, in stored order (winding included). Coordinates of
    # ~80 mm in float32 (STL, PLY): 80 * 6e-8 ~ 5e-6 mm; OBJ's 8 decimals: 5e-9 mm.
    np.testing.assert_allclose(back.vertices[back.faces], surf.vertices[surf.faces], atol=1e-5)
    assert len(back.vertices) == len(surf.vertices)  # STL's shared vertices merged back
    tm = trimesh.Trimesh(back.vertices, back.faces, process=False)
    assert tm.is_watertight and tm.volume > 0  # outward orientation kept


def test_surface_bad_input(tmp_path):
    surf = Surface(np.eye(3), [[0, 1, 2]], "brain")
    with pytest.raises(ValueError, match=r"unsupported surface extension '\.off'.*\.stl, \.ply, \.obj"):
        save_surface(surf, tmp_path / "s.off")
    (tmp_path / "bad.stl").write_bytes(b"\0" * 10)
    with pytest.raises(ValueError, match=r"bad\.stl"):
        load_surface(tmp_path / "bad.stl", "brain")


# ---------------------------------------------------------------------------------------------
# Meshes made elsewhere (issue 15): EIDORS .mat (v5, v7.3), SimNIBS .msh, facing direction

import h5py  # noqa: E402

from jaxhead.electrodes import place_electrodes, spread_positions  # noqa: E402
from jaxhead.fem import build_forward_model, simulate  # noqa: E402
from jaxhead.io import SIMNIBS_TISSUE_MAP, head_facing  # noqa: E402
from jaxhead.protocol import Protocol  # noqa: E402
from jaxhead.tissue import default_sigma  # noqa: E402
from sphere_mesh import structured_sphere_mesh  # noqa: E402

EIDORS_NAMES = ["scalp", "skull", "csf", "grey matter", "white matter"]


@pytest.fixture(scope="module")
def head_like():
    """A four-shell ball with a neck: its lower part sheared backwards (towards -y) like a
    head's neck, so it faces +y (RAS). A shear keeps every tet's volume."""
    m = structured_sphere_mesh(h_mm=24.0)
    x = m.nodes.copy()
    x[:, 1] -= 25.0 * np.clip(-x[:, 2] / 96.0, 0, None) ** 2
    return TetMesh(x, m.tets, m.labels)


def _eidors_ref(mesh):
    # brain tets alternate grey / white matter: both must map to BRAIN by name
    tissue_to_mat = {4: 1, 3: 2, 2: 3}
    ref = np.array([tissue_to_mat.get(int(t), 4 + i % 2) for i, t in enumerate(mesh.labels)])
    return ref


def _rotz(x, deg):
    t = np.radians(deg)
    return x @ np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]]).T


def _reciprocal_forward(mesh):
    """Forward model on the loaded mesh; transfer impedances are reciprocal (V_ab,cd = V_cd,ab)."""
    el = place_electrodes(mesh, spread_positions(mesh, 8), radius_mm=12.0)
    model = build_forward_model(mesh, el)
    p = Protocol(np.array([[0, 4, 2, 6], [2, 6, 0, 4], [1, 5, 3, 7], [3, 7, 1, 5]]))
    v = np.asarray(simulate(model, default_sigma(), p))
    # float64 direct solve: reciprocity holds to ~kappa eps; 1e-8 relative leaves margin
    np.testing.assert_allclose(v[[1, 3]], v[[0, 2]], rtol=1e-8)
    assert np.all(np.abs(v) > 0)


def test_eidors_mat_v5_loads_with_tissues_by_name(tmp_path, head_like):
    scipy.io.savemat(tmp_path / "e.mat", {
        "vtx": head_like.nodes, "tri": (head_like.tets + 1).astype(float),
        "materials": {"ref": _eidors_ref(head_like).astype(float).reshape(-1, 1),
                      "names": np.array(EIDORS_NAMES, dtype=object)}})
    m = load_mesh(tmp_path / "e.mat")
    np.testing.assert_array_equal(m.labels, head_like.labels)
    np.testing.assert_array_equal(m.tets, head_like.tets)
    _reciprocal_forward(m)


def _write_eidors_v73(path, mesh, names, vtx_scale=1.0):
    with h5py.File(path, "w", userblock_size=512) as f:
        for k, a in (("vtx", mesh.nodes * vtx_scale), ("tri", mesh.tets + 1.0)):
            d = f.create_dataset(k, data=np.asarray(a, float).T)  # MATLAB is column-major
            d.attrs["MATLAB_class"] = np.bytes_("double")
        g = f.create_group("materials")
        g.attrs["MATLAB_class"] = np.bytes_("struct")
        d = g.create_dataset("ref", data=_eidors_ref(mesh)[None, :].astype(float))
        d.attrs["MATLAB_class"] = np.bytes_("double")
        refs = f.create_group("#refs#")
        rs = []
        for i, n in enumerate(names):
            c = refs.create_dataset(f"n{i}", data=np.array([ord(ch) for ch in n], np.uint16)[:, None])
            c.attrs["MATLAB_class"] = np.bytes_("char")
            rs.append(c.ref)
        d = g.create_dataset("names", data=np.array(rs, dtype=h5py.ref_dtype)[:, None])
        d.attrs["MATLAB_class"] = np.bytes_("cell")
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file".ljust(116) + b"\0" * 8 + b"\x00\x02IM")


def test_eidors_mat_v73_units_and_unmapped_tissues(tmp_path, head_like):
    _write_eidors_v73(tmp_path / "e73.mat", head_like, EIDORS_NAMES)
    m = load_mesh(tmp_path / "e73.mat")
    np.testing.assert_array_equal(m.labels, head_like.labels)
    np.testing.assert_allclose(m.nodes, head_like.nodes, rtol=0, atol=0)
    # metres: refused unless said
    _write_eidors_v73(tmp_path / "m.mat", head_like, EIDORS_NAMES, vtx_scale=1e-3)
    with pytest.raises(ValueError, match=r"m\.mat.*spans 0\.19.*units='m'"):
        load_mesh(tmp_path / "m.mat")
    np.testing.assert_allclose(load_mesh(tmp_path / "m.mat", units="m").nodes, head_like.nodes,
                               rtol=1e-12)
    # a tissue jaxhead does not know: an error naming it and the fix
    names = EIDORS_NAMES[:4] + ["air"]
    _write_eidors_v73(tmp_path / "air.mat", head_like, names)
    with pytest.raises(ValueError, match=r"air\.mat.*labels 5 \(air\) have no jaxhead tissue.*tissue_map="):
        load_mesh(tmp_path / "air.mat")
    m = load_mesh(tmp_path / "air.mat", tissue_map={"air": "brain"})
    np.testing.assert_array_equal(m.labels, head_like.labels)


def test_eidors_mat_zero_based_is_an_error(tmp_path, head_like):
    scipy.io.savemat(tmp_path / "z.mat", {
        "vtx": head_like.nodes, "tri": head_like.tets.astype(float),
        "materials": {"ref": _eidors_ref(head_like).astype(float),
                      "names": np.array(EIDORS_NAMES, dtype=object)}})
    with pytest.raises(ValueError, match=r"`tri` must hold 1-based .* minimum is 0.*Add 1"):
        load_mesh(tmp_path / "z.mat")


def test_simnibs_msh_needs_and_takes_a_tissue_map(tmp_path, head_like):
    # SimNIBS tags: 1 WM, 2 GM, 3 CSF, 4 bone, 5 scalp, 6 eyes; no PhysicalNames
    simnibs_of = {1: (1, 2), 2: (3,), 3: (4,), 4: (5, 6)}
    tags = np.array([simnibs_of[int(t)][i % len(simnibs_of[int(t)])]
                     for i, t in enumerate(head_like.labels)])
    mm = meshio.Mesh(head_like.nodes, [("tetra", head_like.tets)],
                     cell_data={"gmsh:physical": [tags], "gmsh:geometrical": [tags]})
    meshio.write(tmp_path / "s.msh", mm, file_format="gmsh22", binary=True)
    with pytest.raises(ValueError, match=r"s\.msh.*6 \(eye balls\).*tissue_map='simnibs'"):
        load_mesh(tmp_path / "s.msh")
    with pytest.raises(ValueError, match=r"labels 6 have no jaxhead tissue"):
        load_mesh(tmp_path / "s.msh", tissue_map="simnibs")
    m = load_mesh(tmp_path / "s.msh", tissue_map={**SIMNIBS_TISSUE_MAP, 6: "scalp"})
    np.testing.assert_array_equal(m.labels, head_like.labels)
    _reciprocal_forward(m)


@pytest.mark.parametrize("deg,faces", [(180, "-y"), (90, "-x"), (-90, "+x")])
def test_mesh_facing_away_from_plus_y(tmp_path, head_like, deg, faces):
    assert head_facing(head_like.nodes, head_like.tets)["anterior"] == "+y"
    turned = TetMesh(_rotz(head_like.nodes, deg), head_like.tets, head_like.labels)
    assert head_facing(turned.nodes, turned.tets)["anterior"] == faces
    save_mesh(turned, tmp_path / "t.msh")
    with pytest.raises(ValueError, match=rf"t\.msh.*faces \{faces}.*RAS.*facing='reorient'"):
        load_mesh(tmp_path / "t.msh")
    back = load_mesh(tmp_path / "t.msh", facing="reorient")
    np.testing.assert_allclose(back.nodes, head_like.nodes, atol=1e-9)
    assert load_mesh(tmp_path / "t.msh", facing="ignore").n_tets == head_like.n_tets
    # a ball has no neck: nothing is claimed, nothing refused
    ball = structured_sphere_mesh(h_mm=24.0)
    assert head_facing(ball.nodes, ball.tets)["anterior"] is None
