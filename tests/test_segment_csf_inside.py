"""`SegmentConfig.csf_inside_tables`: CSF that the skull class took when a marrow is as dark as CSF goes back.

Shells of 1 mm voxels stand in for a head: what `bright_skull_inside_tables` must find (bright skull on the
brain's side of the inner table) and must not (a marrow between the tables, a table's one-voxel hole), the
cut it is given (`skull_cut`), the switch, and the step on a segmented scan (the report, and nothing changed
on a skull without such a marrow)."""

from types import SimpleNamespace

import numpy as np
import pytest
from test_segment_marrow import CFG, T1, _atlas, _same_labels, _scan, _shells

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.segment import (MARROW_MIN_SHARE, bright_skull_inside_tables, csf_inside_cut,
                                          segment_reported, skull_cut)
from jaxhead.tissue import Tissue

BG, BRAIN, CSF, SKULL, SCALP = (int(t) for t in Tissue)
#: a child's red marrow as dark as CSF (the MNI152 head's random contrast 1: CSF 0.38, marrow 0.42)
RED = 0.42


def _skull_took_csf():
    """Labels and T1 intensities of nested shells (1 mm): brain to 12, CSF (0.38) labelled skull to 15, an inner
    table (dark) to 17, red marrow (0.42) to 20, an outer table (dark) to 22, scalp to 27, air outside."""
    n = 64
    i = np.arange(n) - (n - 1) / 2
    r = np.sqrt(i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2)
    edges = [12, 15, 17, 20, 22, 27]
    lab = _shells(r, edges, [BRAIN, SKULL, SKULL, SKULL, SKULL, SCALP, BG]).astype(np.uint8)
    y = _shells(r, edges, [T1["wm"], 0.38, T1["bone"], RED, T1["bone"], T1["fat"], 0.0])
    return lab, np.log(np.maximum(y, 1e-3)), r


def test_bright_skull_inside_the_tables_is_the_csf_not_the_marrow():
    lab, y, r = _skull_took_csf()
    cut = 0.5 * (np.log(T1["bone"]) + np.log(RED))
    out = bright_skull_inside_tables(lab, y, cut)
    csf, marrow = (r >= 12) & (r < 15), (r >= 17) & (r < 20)
    # the CSF goes, but for the voxels one step of the 26-neighbourhood from the inner table (up to sqrt 3 mm
    # from it): the tables' one-voxel growth takes them
    assert out[csf & (r < 15 - np.sqrt(3))].all() and out[csf].mean() > 0.4
    assert not out[marrow | ~csf].any()
    assert not bright_skull_inside_tables(lab, y, None).any()
    # labelled CSF is the inside too: the same voxels are found
    lab_csf = lab.copy()
    lab_csf[(r >= 12) & (r < 12.5)] = CSF
    assert not bright_skull_inside_tables(lab_csf, y, cut)[marrow].any()
    # a one-voxel hole in the inner table, as bright as the marrow: the growth closes it, the marrow stays
    c = lab.shape[0] // 2
    line = (c, c, slice(c, None))
    y_hole = y.copy()
    y_hole[line] = np.where((r[line] >= 15) & (r[line] < 17), np.log(RED), y[line])
    assert not bright_skull_inside_tables(lab, y_hole, cut)[marrow].any()
    # a channel of CSF through the inner table: the marrow whose rays reach it is no longer walled
    tube = (slice(c - 1, c + 2), slice(c - 1, c + 2), slice(c, None))
    lab[tube] = np.where((r[tube] >= 15) & (r[tube] < 17), CSF, lab[tube])
    out = bright_skull_inside_tables(lab, y, cut)
    assert 0.0 < out[marrow].mean() < 0.5


def _fit_with(gaussians):
    """A stand-in for a fit's (posteriors, EMResult, EMOptions): `gaussians` is [(class, mean, weight), ...]."""
    cls, means, weights = (np.array(v) for v in zip(*gaussians))
    return None, SimpleNamespace(params=SimpleNamespace(means=means, weights=weights)), SimpleNamespace(
        component_class=cls)


def test_skull_cut_is_the_midpoint_of_the_skull_gaussians_with_weight():
    brain = [(BRAIN, -0.4, 0.6), (BRAIN, 0.0, 0.4)]
    assert skull_cut(_fit_with(brain + [(SKULL, -2.1, 0.3), (SKULL, -0.9, 0.7)])) == pytest.approx(-1.5)
    assert skull_cut(_fit_with(brain + [(SKULL, -2.1, 0.3), (SKULL, -0.9, 0.7), (SKULL, 0.1, 0.0)])) == \
        pytest.approx(-1.5)  # an emptied Gaussian is not counted
    assert skull_cut(_fit_with(brain + [(SKULL, -2.1, 1.0), (SKULL, -0.9, 0.5 * MARROW_MIN_SHARE)])) is None


def test_csf_inside_cut_only_where_every_skull_gaussian_is_darker_than_the_brain():
    brain = [(BRAIN, -0.4, 0.6), (BRAIN, 0.0, 0.4)]
    child = brain + [(SKULL, -2.1, 0.3), (SKULL, -0.9, 0.7)]  # the marrow's Gaussian below the brain: CSF-like
    assert csf_inside_cut(_fit_with(child)) == pytest.approx(skull_cut(_fit_with(child)))
    adult = brain + [(SKULL, -2.3, 0.5), (SKULL, -1.6, 0.3), (SKULL, 0.2, 0.2)]  # a fat-bright marrow
    assert skull_cut(_fit_with(adult)) is not None and csf_inside_cut(_fit_with(adult)) is None
    assert csf_inside_cut(_fit_with(child + [(SKULL, 0.2, 0.5 * MARROW_MIN_SHARE)])) == pytest.approx(-1.5)
    assert csf_inside_cut(_fit_with(brain + [(SKULL, -2.1, 1.0)])) is None  # one Gaussian: no cut
    assert csf_inside_cut(_fit_with([(SKULL, -2.1, 0.3), (SKULL, -0.9, 0.7)])) is None  # no brain Gaussian


def test_segment_config_csf_inside_tables():
    assert SegmentConfig(modality="mri").csf_inside_tables_on()  # on for MRI since session 27
    assert not SegmentConfig(modality="mri", csf_inside_tables=False).csf_inside_tables_on()
    assert not SegmentConfig(modality="ct").csf_inside_tables_on()
    with pytest.raises(ValueError, match="csf_inside_tables.*modality='mri'"):
        SegmentConfig(modality="ct", csf_inside_tables=True)


def test_on_a_segmented_scan_reported_and_coarse_voxels_skipped():
    """A skull of dark bone under a right atlas: the step runs after the EM and after the layer split, says
    what it found in the report, and moves no more than speckle (nothing here to take back), so the labels are
    those with it off; at 2 mm it is skipped and said so."""
    vol, _ = _scan(marrow=False)
    atlas = _atlas(skull_outer_mm=29.0)
    cfg = {**CFG, "layer_split": True}
    on, seg = segment_reported(vol, atlas, SegmentConfig(**cfg, csf_inside_tables=True))
    off, _ = segment_reported(vol, atlas, SegmentConfig(**cfg, csf_inside_tables=False))
    report = seg.registration["csf_inside_tables"]
    assert set(report) == {"before_layer_split", "after_layer_split"}
    for step in report.values():
        assert step["voxels"] == 0 and step.get("found", 0) < MARROW_MIN_SHARE * (on.labels == SKULL).sum()
    _same_labels(on, off)
    coarse = type(vol)(vol.data[::2, ::2, ::2], np.diag([2.0, 2.0, 2.0, 1.0]))
    _, seg2 = segment_reported(coarse, atlas, SegmentConfig(**cfg, csf_inside_tables=True))
    assert "MARROW_MAX_VOXEL_MM" in seg2.registration["csf_inside_tables"]["before_layer_split"]["skipped"]
