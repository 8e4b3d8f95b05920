"""`marrow_tables` (MRI): the compact tables around a fat-bright marrow that a scanner's blur gave to CSF or the
scalp go back to the skull; nothing else moves."""

import numpy as np
import pytest
from scipy import ndimage

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.segment import MARROW_TABLE_MM, marrow_tables
from jaxhead.tissue import Tissue

BG, BRAIN, CSF, SKULL, SCALP = (int(t) for t in Tissue)


def _shells(n=48, vox=1.0):
    """Brain to 10 mm, CSF to 13, inner table to 14.5, marrow to 18.5, outer table to 20, scalp to 23; the EM's
    labels give the inner table to CSF and the outer to the scalp (a blurred scan's error), intensities: marrow
    and scalp fat bright (1.0), tables and CSF dark (0.3), brain 0.7."""
    i = (np.arange(n) - (n - 1) / 2) * vox
    r = np.sqrt(i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2)
    truth = np.select([r < 10, r < 13, r < 20, r < 23], [BRAIN, CSF, SKULL, SCALP], BG)
    labels = np.select([r < 10, r < 14.5, r < 18.5, r < 23], [BRAIN, CSF, SKULL, SCALP], BG)
    y = np.select([r < 10, r < 14.5, r < 18.5, r < 20, r < 23], [0.7, 0.3, 1.0, 0.3, 1.0], 0.0)
    tables = ((r >= 13) & (r < 14.5)) | ((r >= 18.5) & (r < 20))
    return r, truth, labels, y, tables


def test_the_blurred_tables_go_back_to_the_skull_and_nothing_else():
    r, truth, labels, y, tables = _shells()
    found = marrow_tables(labels, y, 0.65, (1.0, 1.0, 1.0))
    assert not (found & ~tables).any()  # no CSF or scalp beyond a table's reach
    # on a 1 mm grid a 1.5 mm shell's voxels lie up to ~1.9 mm from the marrow's nearest voxel centre
    assert found.sum() > 0.8 * tables.sum()

    def skull_dice(lab):
        return 2 * ((lab == SKULL) & (truth == SKULL)).sum() / ((lab == SKULL).sum() + (truth == SKULL).sum())

    assert skull_dice(labels) < 0.75 and skull_dice(np.where(found, SKULL, labels)) > 0.9


def test_is_the_full_grid_distance_rule_by_brute_force():
    """The bounding-box distance transform equals the rule on the whole grid (anisotropic voxels), the exposed
    marrow found by loops over the six face neighbours."""
    rng = np.random.default_rng(0)
    labels = rng.choice([BG, CSF, SKULL, SCALP], size=(20, 24, 18), p=[0.3, 0.3, 0.1, 0.3]).astype(np.uint8)
    labels[:6] = CSF  # the marrow's box does not reach every side
    y = rng.uniform(0.0, 1.0, labels.shape)
    vox = (0.9, 1.1, 1.3)
    for reach in (1.0, 1.5, 2.5):
        outside = (labels == CSF) | (labels == SCALP)
        exposed = np.zeros(labels.shape, bool)  # bright skull with a CSF or scalp face neighbour, by loops
        for i, j, k in zip(*np.nonzero((labels == SKULL) & (y > 0.5))):
            for d in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
                q = (i + d[0], j + d[1], k + d[2])
                if all(0 <= a < n for a, n in zip(q, labels.shape)) and outside[q]:
                    exposed[i, j, k] = True
        near = ndimage.distance_transform_edt(~exposed, sampling=vox) <= reach
        expect = near & outside & (y <= 0.5)
        np.testing.assert_array_equal(marrow_tables(labels, y, 0.5, vox, reach), expect)


def test_tables_labelled_skull_keep_the_csf_and_scalp_beyond_them():
    """Sharp thin tables, labelled skull: the marrow is not exposed, so nothing moves, though the CSF and the
    scalp lie within the reach of the marrow (1 mm tables, 1.5 mm reach)."""
    r, truth, labels, y, tables = _shells()
    thin = np.select([r < 10, r < 13.5, r < 14.5, r < 18.5, r < 19.5, r < 23], [BRAIN, CSF, SKULL, SKULL, SKULL, SCALP], BG)
    y_thin = np.select([r < 10, r < 14.5, r < 18.5, r < 19.5, r < 23], [0.7, 0.3, 1.0, 0.3, 1.0], 0.0)
    assert not marrow_tables(thin, y_thin, 0.65, (1.0,) * 3, reach_mm=1.5).any()


def test_nothing_without_a_fat_bright_marrow():
    r, truth, labels, y, tables = _shells()
    assert not marrow_tables(labels, y, None, (1.0,) * 3).any()  # the skull learnt no fat-bright Gaussian
    assert not marrow_tables(labels, np.minimum(y, 0.5), 0.65, (1.0,) * 3).any()  # no skull above the cut
    with pytest.raises(ValueError, match="reach_mm"):
        marrow_tables(labels, y, 0.65, (1.0,) * 3, reach_mm=0.0)


def test_marrow_tables_is_an_mri_option():
    assert SegmentConfig(modality="mri").marrow_tables_on() in (True, False)
    assert not SegmentConfig(modality="ct").marrow_tables_on()
    assert not SegmentConfig(modality="mri", marrow_tables=False).marrow_tables_on()
    with pytest.raises(ValueError, match="marrow_tables"):
        SegmentConfig(modality="ct", marrow_tables=True)
    assert MARROW_TABLE_MM > 0
