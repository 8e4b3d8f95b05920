"""Expected failures are one clear ValueError (issue 14, "Failures are one line").

Each test is a case that gave a traceback, a silent wrong result or a misleading message
before: a singular affine, a 4000 mm voxel size, text in a CSV's data row, an Inf conductivity,
a float32 FEM.
"""

import jax
import nibabel as nib
import numpy as np
import pytest

from jaxhead import io
from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import build_forward_model, simulate
from jaxhead.protocol import load_voltages, opposite
from sphere_mesh import structured_sphere_mesh


def singular_affine_nifti(path):
    """A NIfTI whose sform has a zero column (nibabel refuses to write one via the affine)."""
    data = np.random.default_rng(0).random((10, 10, 10)).astype(np.float32)
    img = nib.Nifti1Image(data, np.eye(4))
    hdr = img.header
    hdr.set_qform(None, code=0)
    hdr["sform_code"] = 1
    hdr["srow_x"], hdr["srow_y"], hdr["srow_z"] = [0, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0]
    nib.save(nib.Nifti1Image(data, None, hdr), str(path))
    return path


def huge_voxel_nifti(path, voxel_mm=4000.0):
    data = np.random.default_rng(0).random((10, 10, 10)).astype(np.float32)
    nib.save(nib.Nifti1Image(data, np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])), str(path))
    return path


def test_singular_affine_is_a_value_error_and_info_reports_it(tmp_path):
    # Was: TypeError from nibabel's aff2axcodes, in load_volume and in `jaxhead info`.
    path = singular_affine_nifti(tmp_path / "sing.nii.gz")
    with pytest.raises(ValueError, match=r"sing.nii.gz.*affine.*singular.*fix the header"):
        io.load_volume(path)
    assert "singular" in io.info(path)["orientation"]


def test_absurd_voxel_size_is_refused_with_the_memory_estimate(tmp_path):
    # Was: an attempt to allocate tens of TiB (1.24 PiB at 1 mm).
    vol = io.load_volume(huge_voxel_nifti(tmp_path / "big.nii.gz"))
    with pytest.raises(ValueError, match=r"would need about .*TiB.*available.*4000.*implausible"):
        io.resample(vol, 2.0)
    small = io.resample(vol, 8000.0)  # what fits is still done
    assert small.shape == (5, 5, 5)


def test_text_in_a_data_row_is_not_a_header(tmp_path):
    # Was: a first data row with a typo was skipped as a header, and the file then had one row
    # too few (or, with one row extra, was silently shifted).
    p = opposite(8)
    rows = p.rows + 1
    lines = [f"{r[0]},{r[1]},{r[2]},{r[3]},{1e-3 * (i + 1)}" for i, r in enumerate(rows)]
    lines[0] = lines[0].replace("0.001", "0.0O1")  # letter O
    path = tmp_path / "v.csv"
    path.write_text("source,sink,meas_plus,meas_minus,volts\n" + "\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"v.csv:2: not numbers: \['0.0O1'\]"):
        load_voltages(path, p)
    lines[0] = lines[0].replace("0.0O1", "0.001")
    path.write_text("source,sink,meas_plus,meas_minus,volts\n" + "\n".join(lines) + "\n")
    assert load_voltages(path, p)[0] == 1e-3  # a real header is still skipped


@pytest.fixture(scope="module")
def small_model():
    mesh = structured_sphere_mesh(h_mm=24.0)
    return build_forward_model(mesh, place_electrodes(mesh, spread_positions(mesh, 8),
                                                      radius_mm=10.0))


def test_non_finite_sigma_is_named(small_model):
    # Was: "`sigma` must be finite and > 0 S/m, got min 0.018" for an Inf.
    with pytest.raises(ValueError, match=r"got \[inf\] at index \[2\]"):
        simulate(small_model, np.array([0.3, 1.79, np.inf, 0.44]), opposite(8))
    with pytest.raises(ValueError, match=r"got \[nan, -1.0\] at index \[0, 3\]"):
        simulate(small_model, np.array([np.nan, 1.79, 0.018, -1.0]), opposite(8))


def test_the_fem_refuses_float32_unless_asked(small_model):
    # Was: with jax_enable_x64 off the FEM ran in float32 (1e-4 relative error) without a word.
    mesh = structured_sphere_mesh(h_mm=24.0)
    el = place_electrodes(mesh, spread_positions(mesh, 8), radius_mm=10.0)
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(ValueError, match="jax_enable_x64.*allow_float32=True"):
            build_forward_model(mesh, el)
        build_forward_model(mesh, el, allow_float32=True)  # asked for: allowed
    finally:
        jax.config.update("jax_enable_x64", True)
