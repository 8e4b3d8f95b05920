"""Label-map perturbations on concentric-sphere label maps: thicknesses and volumes vs geometry."""

import numpy as np
import pytest
from test_fem_assembly import small_model

from jaxhead.study import jitter_electrodes, perturb_labels
from jaxhead.volume import LabelMap, default_affine

RADII = (30.0, 34.0, 40.0, 46.0)  # brain, CSF, skull, scalp outer radii (mm)


@pytest.fixture(scope="module")
def spheres():
    n = 104
    aff = default_affine(1.0, (n, n, n))
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    xyz = ijk @ aff[:3, :3].T + aff[:3, 3]
    r = np.linalg.norm(xyz, axis=1).reshape(n, n, n)
    L = np.zeros((n, n, n), np.uint8)
    for t, rad in zip((4, 3, 2, 1), RADII[::-1]):
        L[r <= rad] = t
    return LabelMap(L, aff), r


def shell_vol(a, b):
    return 4 / 3 * np.pi * (b**3 - a**3)


def count(lm, t):
    return int((lm.labels == t).sum())


def test_dilate_and_erode_move_the_interface_by_k_voxels(spheres):
    lm, r = spheres
    big, d = perturb_labels(lm, "dilate", tissue="brain", amplitude=2, seed=0)
    # 6-connected steps: the interface moves 2 mm along axes, 2/sqrt(3) mm along diagonals
    gain = count(big, 1) - count(lm, 1)
    area = 4 * np.pi * RADII[0] ** 2
    assert 2 / np.sqrt(3) * area * 0.9 < gain < 2 * area * 1.1
    assert count(big, 2) == count(lm, 2) - gain and d["voxels_changed"] == gain
    small, d = perturb_labels(lm, "erode", tissue="brain", amplitude=2)
    loss = count(lm, 1) - count(small, 1)
    assert 2 / np.sqrt(3) * area * 0.8 < loss < 2 * area * 1.1
    assert count(small, 2) == count(lm, 2) + loss
    # the scalp dilates into the background
    out, _ = perturb_labels(lm, "dilate", tissue="scalp", amplitude=1)
    assert count(out, 4) > count(lm, 4) and count(out, 0) < count(lm, 0)


@pytest.mark.parametrize("factor", [0.5, 1.5])
def test_skull_scale_gives_the_scaled_thickness(spheres, factor):
    lm, r = spheres
    out, d = perturb_labels(lm, "skull_scale", amplitude=factor)
    outer = RADII[1] + factor * (RADII[2] - RADII[1])
    # voxel-centre sampling of a shell: volume within a voxel's worth of area (~1 mm) of exact
    exact = shell_vol(RADII[1], min(outer, RADII[3]))
    assert count(out, 3) == pytest.approx(exact, rel=0.12)
    assert count(out, 1) == count(lm, 1) and count(out, 2) == count(lm, 2)
    assert d["factor"] == factor and d["voxels_changed"] > 0


def test_csf_removed_and_thinned(spheres):
    lm, _ = spheres
    out, _ = perturb_labels(lm, "csf_scale", amplitude=0.0)
    assert count(out, 2) == 0 and count(out, 1) == count(lm, 1) + count(lm, 2)
    half, _ = perturb_labels(lm, "csf_scale", amplitude=0.5)
    assert count(half, 2) == pytest.approx(shell_vol(32.0, 34.0), rel=0.15)
    assert count(half, 3) == count(lm, 3)


def test_skull_hole_is_seeded_and_closing_undoes_it(spheres):
    lm, _ = spheres
    a, da = perturb_labels(lm, "skull_hole", amplitude=5.0, seed=3)
    b, _ = perturb_labels(lm, "skull_hole", amplitude=5.0, seed=3)
    c, dc = perturb_labels(lm, "skull_hole", amplitude=5.0, seed=4)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert da["centre_mm"] != dc["centre_mm"]
    lost = count(lm, 3) - count(a, 3)
    # a cylinder of radius 5 through a 6 mm shell: ~pi 25 x 6 mm^3
    assert lost == pytest.approx(np.pi * 25 * 6, rel=0.35)
    closed, d = perturb_labels(a, "skull_close", amplitude=8.0)
    # closing fills the cylinder but rounds its rim on the curved outer surface at voxel scale
    assert count(lm, 3) - count(closed, 3) < 0.25 * lost and d["voxels_changed"] >= 0.75 * lost
    assert count(closed, 3) <= count(lm, 3) + 0.05 * lost  # it adds no skull elsewhere


def test_none_is_the_identity(spheres):
    lm, _ = spheres
    out, d = perturb_labels(lm, "none", amplitude=0.0)
    np.testing.assert_array_equal(out.labels, lm.labels)
    assert d["voxels_changed"] == 0


def test_unknown_kind_and_bad_amplitude(spheres):
    lm, _ = spheres
    with pytest.raises(ValueError, match="unknown label perturbation 'wobble'"):
        perturb_labels(lm, "wobble", amplitude=1)
    with pytest.raises(ValueError, match="factor.*-1"):
        perturb_labels(lm, "skull_scale", amplitude=-1.0)
    with pytest.raises(ValueError, match="unknown tissue"):
        perturb_labels(lm, "dilate", tissue="bone", amplitude=1)


def test_electrode_jitter():
    mesh, elec = small_model(h_mm=24.0, n_elec=6)
    same, d0 = jitter_electrodes(mesh, elec, 0.0, seed=1, radius_mm=20.0)
    np.testing.assert_allclose(same.centres, elec.centres, atol=1e-9)
    moved, d = jitter_electrodes(mesh, elec, 4.0, seed=1, radius_mm=20.0)
    again, _ = jitter_electrodes(mesh, elec, 4.0, seed=1, radius_mm=20.0)
    np.testing.assert_array_equal(moved.centres, again.centres)
    # tangential 2D Gaussian of sd 4: mean |shift| = 4 sqrt(pi / 2) ~ 5 mm; 6 draws
    assert 1.0 < d["mean_shift_mm"] < 10.0
    with pytest.raises(ValueError, match="sd_mm"):
        jitter_electrodes(mesh, elec, -1.0)
