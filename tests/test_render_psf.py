"""The scanner's point-spread function in the synthetic scans (`templates.render(psf_fwhm_mm=...)`, `blurred`):
checked against the analytic blur of a step edge (an error function), the conservation of the total signal, and
voxel sizes per axis."""

import numpy as np
import pytest
from scipy.special import erf

from jaxhead.segmentation.templates import Anatomy, blurred, render


def _half_space(shape=(64, 8, 8), voxel_mm=(0.5, 0.5, 0.5), axis=0) -> Anatomy:
    """White matter where the index along `axis` is >= half the axis, air elsewhere (an edge on a voxel face)."""
    fr = np.zeros((6, *shape), np.float32)
    idx = np.indices(shape)[axis]
    fr[2] = idx >= shape[axis] // 2
    fr[0] = 1.0 - fr[2]
    return Anatomy(fr, np.diag([*voxel_mm, 1.0]), "half space")


def test_a_step_edge_is_blurred_into_the_error_function_of_its_fwhm():
    fwhm, vox = 3.0, 0.5  # sd 2.5 voxels: the sampled kernel is within 2e-3 of the continuous one
    img = render(_half_space(), "mri", texture=False, psf_fwhm_mm=fwhm).data
    x = (np.arange(64) - 32 + 0.5) * vox  # voxel centres, mm from the edge (the face between voxels 31 and 32)
    sd = fwhm / (2 * np.sqrt(2 * np.log(2)))
    expected = 0.5 * (1 + erf(x / (sd * np.sqrt(2))))  # white matter = 1, air = 0
    np.testing.assert_allclose(img[:, 4, 4], expected, atol=2e-3)
    assert np.ptp(img, axis=(1, 2)).max() < 1e-12  # no change across the edge's plane


def test_no_blur_is_the_image_itself_and_blur_conserves_the_total():
    a = _half_space()
    sharp = render(a, "mri", texture=False, noise=0.03, bias=0.2, seed=3)
    np.testing.assert_array_equal(render(a, "mri", texture=False, noise=0.03, bias=0.2, seed=3, psf_fwhm_mm=0.0).data,
                                  sharp.data)
    img = np.random.default_rng(0).random((20, 24, 16))
    out = blurred(img, 1.5, (1.0, 0.8, 1.2))
    assert abs(out.sum() - img.sum()) < 1e-9 * img.sum()  # reflected edges: nothing leaves the grid
    assert out.std() < img.std()


def test_the_width_is_in_mm_on_every_axis_whatever_its_voxels():
    # the same edge on an axis of 0.5 mm and one of 1.0 mm voxels: one profile in mm
    fine = render(_half_space((64, 8, 8), (0.5, 1.0, 1.0), axis=0), "mri", texture=False, psf_fwhm_mm=3.0).data[:, 4, 4]
    coarse = render(_half_space((8, 32, 8), (0.5, 1.0, 1.0), axis=1), "mri", texture=False, psf_fwhm_mm=3.0).data[4, :, 4]
    # voxel centres at +-0.25, +-0.75 mm ... (fine) and +-0.5, +-1.5 mm ... (coarse): compare at the coarse ones,
    # interpolating the fine profile linearly between its centres
    x_fine = (np.arange(64) - 32 + 0.5) * 0.5
    x_coarse = (np.arange(32) - 16 + 0.5) * 1.0
    np.testing.assert_allclose(coarse, np.interp(x_coarse, x_fine, fine), atol=0.02)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_a_bad_width_is_named(bad):
    with pytest.raises(ValueError, match="psf_fwhm_mm"):
        render(_half_space(), "mri", psf_fwhm_mm=bad)
