"""Tests of jaxhead.geometry.surface on nested spheres (analytic volumes, centres) and hand-made meshes."""

import json
import logging

import numpy as np
import pytest
import trimesh

from jaxhead.geometry import surface as surface_module
from jaxhead.geometry.layers import make_layers
from jaxhead.geometry.surface import (
    Surface, SurfaceConfig, _tri_tri_intersect, check_surface, edge_lengths, euler_number,
    extract_surfaces, extract_surfaces_reported, self_intersections, surface_area_mm2,
    surface_gap_mm, surface_volume_mm3, to_trimesh)
from jaxhead.tissue import TISSUES, Tissue
from jaxhead.volume import LabelMap, default_affine

VOX = 2.5
RADII = (24.0, 30.0, 36.0, 42.0)  # BRAIN, CSF, SKULL, SCALP outer radii (mm): shells >= 2 voxels
CENTRE = np.array([10.0, -20.0, 5.0])


def sphere_labels(radii=RADII, vox=VOX, flip_x=True, centre=CENTRE):
    """Concentric spheres about `centre` (world mm) on a grid whose affine flips x (det < 0)."""
    n = int(2 * radii[-1] / vox) + 8
    aff = default_affine(vox, (n, n, n))
    if flip_x:
        aff[0, 0] = -vox
        aff[0, 3] = -aff[0, 3]
    aff[:3, 3] += centre
    ijk = np.indices((n, n, n)).reshape(3, -1).T
    xyz = (ijk @ aff[:3, :3].T + aff[:3, 3]).reshape(n, n, n, 3)
    r = np.linalg.norm(xyz - centre, axis=-1)
    L = np.zeros((n, n, n), np.uint8)
    for rad, t in zip(radii[::-1], (4, 3, 2, 1)):
        L[r <= rad] = t
    return LabelMap(L, aff)


#: Edges well below the spheres' radii (h <= R / 8): the chordal volume loss of a triangulated
#: sphere, ~3 h^2 / (8 R^2), stays below 0.6 % so the 3 % volume bars below test marching cubes
#: and smoothing, not the triangle size. (The defaults, 4-6 mm, are sized for adult heads.)
SPHERE_CFG = SurfaceConfig(edge_mm={"brain": 3.0, "csf": 2.0, "skull": 2.5, "scalp": 3.0})


@pytest.fixture(scope="module")
def spheres_result():
    labels = sphere_labels()
    layers = make_layers(labels)
    surfaces, report = extract_surfaces_reported(layers, SPHERE_CFG)
    return labels, layers, surfaces, report


def test_surfaces_are_closed_manifold_outward(spheres_result):
    _, _, surfaces, report = spheres_result
    assert list(surfaces) == list(TISSUES)
    for t, s in surfaces.items():
        assert s.tissue == t
        chk = check_surface(s)
        assert chk.ok, (t, chk.problems())
        # independent checks by trimesh
        tm = to_trimesh(s)
        assert tm.is_watertight and tm.is_winding_consistent and tm.is_volume, t
        assert tm.body_count == 1 and tm.volume > 0, t
        assert report[t].self_intersections == 0


def test_volumes_match_voxels_and_analytic_spheres(spheres_result):
    labels, layers, surfaces, report = spheres_result
    vox_vol = VOX ** 3
    for t, r in zip(TISSUES, RADII):
        vol = surface_volume_mm3(surfaces[t])
        solid = int(((layers.labels >= 1) & (layers.labels <= int(t))).sum()) * vox_vol
        # marching cubes at level 0.5 of the (slightly smoothed) mask encloses the voxel volume up
        # to O(curvature x sigma^2) shrinkage and staircase sampling: within 3% at r >= 10 voxels
        assert vol == pytest.approx(solid, rel=0.03), t
        assert report[t].voxel_volume_mm3 == pytest.approx(solid)
        # the digital sphere's volume is itself within O(voxel / r) of the analytic one
        assert vol == pytest.approx(4 / 3 * np.pi * r ** 3, rel=0.04), t
        assert report[t].volume_mm3 == pytest.approx(vol)


def test_world_coordinates_follow_a_flipped_affine(spheres_result):
    labels, _, surfaces, _ = spheres_result
    assert np.linalg.det(labels.affine[:3, :3]) < 0
    for t, r in zip(TISSUES, RADII):
        v = surfaces[t].vertices
        # vertices are nearly uniform on the sphere, so their mean is the centre to ~0.1 voxel; a
        # mishandled flip would put it 20 mm away (x -> -x)
        np.testing.assert_allclose(v.mean(axis=0), CENTRE, atol=0.3)
        radius = np.linalg.norm(v - CENTRE, axis=1)
        assert radius.mean() == pytest.approx(r, rel=0.03)
        assert np.ptp(radius) < 2 * VOX  # a sphere, not a distorted blob


def test_edge_lengths_near_target(spheres_result):
    _, _, surfaces, report = spheres_result
    targets = SPHERE_CFG.edges()
    for t, s in surfaces.items():
        L = edge_lengths(s)
        assert np.median(L) == pytest.approx(targets[t], rel=0.3), t
        # Botsch-Kobbelt keeps edges within [4/5, 4/3] of the target, up to tangential relaxation
        assert np.percentile(L, 5) > 0.6 * targets[t] and np.percentile(L, 95) < 1.5 * targets[t], t
        assert report[t].edge_mm[2] == pytest.approx(np.median(L))
        assert report[t].area_mm2 == pytest.approx(surface_area_mm2(s))


def test_nested_with_min_gap(spheres_result):
    _, _, surfaces, report = spheres_result
    gap = SPHERE_CFG.min_gap_mm
    for inner, outer in ((Tissue.BRAIN, Tissue.CSF), (Tissue.CSF, Tissue.SKULL), (Tissue.SKULL, Tissue.SCALP)):
        g = surface_gap_mm(surfaces[inner], surfaces[outer])
        assert g >= gap
        assert report[inner].gap_to_outer_mm >= gap
        # independent: trimesh's signed distance (positive inside) of inner vertices (a sample)
        pts = np.random.default_rng(0).permutation(surfaces[inner].vertices)[:400]
        sd = trimesh.proximity.signed_distance(to_trimesh(surfaces[outer]), pts)
        assert sd.min() >= gap * (1 - 1e-9), (inner, sd.min())


def test_report_dict_and_str(spheres_result):
    *_, report = spheres_result
    d = report.to_dict()
    json.dumps(d)
    assert set(d["surfaces"]) == {"brain", "csf", "skull", "scalp"}
    assert "BRAIN" in str(report) and "faces" in str(report)
    assert report[Tissue.SCALP].gap_to_outer_mm is None


# ---------------------------------------------------------------------------------------------
# the gap is enforced, counted, and impossible gaps raise


def test_gap_enforced_by_pushing_inner_vertices():
    # CSF one voxel thick after make_layers' 3x3x3 rule: surfaces ~2 voxels (5 mm) apart at most,
    # closer on the diagonals; ask for 3 mm
    layers = make_layers(sphere_labels(radii=(24.0, 27.0, 33.0, 38.0), flip_x=False))
    cfg = SurfaceConfig(min_gap_mm=3.0)
    surfaces, report = extract_surfaces_reported(layers, cfg)
    assert report[Tissue.BRAIN].gap_vertices_moved > 0
    assert 0 < report[Tissue.BRAIN].max_move_mm < 3.0
    assert surface_gap_mm(surfaces[Tissue.BRAIN], surfaces[Tissue.CSF]) >= 3.0
    assert check_surface(surfaces[Tissue.BRAIN]).ok


def _ridge_under_valley(g: float):
    """A convex inner body whose top ridge (an edge along x at z = 5) passes g mm under the
    valley crease (an edge along y at z = 5 + g) of a coarse outer box: every vertex of either
    surface is more than 2.5 mm from the other surface, the surfaces only g mm apart."""
    from scipy.spatial import ConvexHull
    P = np.array([[-8, 0, 5], [8, 0, 5], [0, -8, -3], [0, 8, -3], [0, 0, -8]], float)
    inner = trimesh.Trimesh(P, ConvexHull(P).simplices)
    inner.fix_normals()
    z = 5.0 + g
    OV = np.array([[-12, -12, 9], [12, -12, 9], [12, 12, 9], [-12, 12, 9], [0, -12, z], [0, 12, z],
                   [-12, -12, -12], [12, -12, -12], [12, 12, -12], [-12, 12, -12]], float)
    OF = np.array([[0, 4, 5], [0, 5, 3], [4, 1, 2], [4, 2, 5],  # the two halves of the top
                   [6, 7, 1], [6, 1, 4], [6, 4, 0], [9, 8, 2], [9, 2, 5], [9, 5, 3],  # front, back
                   [7, 8, 2], [7, 2, 1], [6, 9, 3], [6, 3, 0], [6, 7, 8], [6, 8, 9]])
    outer = trimesh.Trimesh(OV, OF)
    outer.fix_normals()
    return (Surface(inner.vertices, inner.faces, Tissue.BRAIN),
            Surface(outer.vertices, outer.faces, Tissue.CSF))


def test_gap_between_vertices_found_by_denser_samples():
    """Two surfaces closer than the gap only between their vertices (a ridge under a valley, the
    case that stopped the ANTs head at 2 mm): separating the vertices does nothing, the exact
    gap stays short; the denser samples on the faces separate them to the gap."""
    inner, outer = _ridge_under_valley(0.2)
    assert check_surface(outer).ok and check_surface(inner).ok
    assert surface_gap_mm(inner, outer) == pytest.approx(0.2, abs=1e-6)
    new, n, _ = surface_module._separate(inner, outer, 0.5, 20, 5.0, density=1)
    assert n == 0 and surface_gap_mm(new, outer) < 0.21
    for density in surface_module._GAP_DENSITIES[1:]:
        new, n, _ = surface_module._separate(inner, outer, 0.5, 20, 5.0, density=density)
        assert n > 0 and surface_gap_mm(new, outer) >= 0.5, density


def test_impossible_gap_raises_naming_tissues():
    layers = make_layers(sphere_labels(radii=(24.0, 27.0, 33.0, 38.0), flip_x=False))
    # both the SCALP (6 mm) and the SKULL (5 mm) shells are thinner than 15 mm; which is named
    # first depends on the edge lengths (the move limit is 1.1 min_gap + edge / 2)
    with pytest.raises(ValueError, match=r"SCALP shell is thinner than min_gap_mm=15.*SKULL surface"):
        extract_surfaces(layers, SurfaceConfig(min_gap_mm=15.0, edge_mm=SPHERE_CFG.edge_mm))
    with pytest.raises(ValueError, match=r"(SCALP|SKULL) shell is thinner than min_gap_mm=15.*(SKULL|CSF) surface"):
        extract_surfaces(layers, SurfaceConfig(min_gap_mm=15.0))


# ---------------------------------------------------------------------------------------------
# options


def test_decimate_option_and_custom_edges():
    layers = make_layers(sphere_labels(flip_x=False))
    cfg = SurfaceConfig(remesh="decimate", edge_mm={"brain": 4.0, "csf": 3.0, "skull": 3.0, "scalp": 5.0},
                        presmooth_sigma_voxels=0.0)
    surfaces, report = extract_surfaces_reported(layers, cfg)
    for t, s in surfaces.items():
        assert check_surface(s).ok, t
        # quadric decimation hits the face count, not the edge length: looser (50%)
        assert np.median(edge_lengths(s)) == pytest.approx(cfg.edges()[t], rel=0.5), t


def test_extract_surfaces_logs_report(caplog):
    layers = make_layers(sphere_labels(radii=(12.0, 15.0, 18.0, 21.0), vox=3.0, flip_x=False))
    with caplog.at_level(logging.INFO, logger="jaxhead.geometry.surface"):
        surfaces = extract_surfaces(layers, SurfaceConfig(edge_mm=3.0))
    assert "extract_surfaces" in caplog.text
    assert len(surfaces) == 4


def test_kept_ventricles_are_filled_and_reported():
    from jaxhead.geometry.layers import LayerConfig

    labels = sphere_labels(radii=(15.0, 18.0, 21.0, 24.0), vox=3.0, flip_x=False, centre=np.zeros(3))
    L = labels.labels.copy()
    ijk = np.indices(L.shape).reshape(3, -1).T
    r = np.linalg.norm(ijk @ labels.affine[:3, :3].T + labels.affine[:3, 3], axis=1).reshape(L.shape)
    L[r <= 6.0] = 2
    n_v = int((r <= 6.0).sum())
    layers = make_layers(LabelMap(L, labels.affine), LayerConfig(ventricles="keep"))
    assert (layers.labels == 2).sum() > n_v  # kept
    surfaces, rep = extract_surfaces_reported(layers, SurfaceConfig(edge_mm=3.0))
    assert rep[Tissue.BRAIN].cavity_voxels == n_v  # the brain solid is filled, and it says so
    assert rep[Tissue.CSF].cavity_voxels == 0
    assert check_surface(surfaces[Tissue.BRAIN]).n_components == 1


# ---------------------------------------------------------------------------------------------
# bad input


def test_not_nested_labels_rejected():
    labels = sphere_labels(radii=(24.0, 25.0, 33.0, 38.0), flip_x=False)  # CSF under one voxel
    with pytest.raises(ValueError, match="not strictly nested.*make_layers"):
        extract_surfaces(labels)


def test_border_and_missing_tissue_rejected():
    labels = sphere_labels(flip_x=False)
    L = labels.labels.copy()
    c = L.shape[0] // 2
    L[0, c, c] = 4
    with pytest.raises(ValueError, match="SCALP on x=0.*pad"):
        extract_surfaces(LabelMap(L, labels.affine))
    L = labels.labels.copy()
    L[L == 3] = 4
    with pytest.raises(ValueError, match="no SKULL voxels"):
        extract_surfaces(LabelMap(L, labels.affine))
    with pytest.raises(ValueError, match="LabelMap"):
        extract_surfaces(labels.labels)


def test_config_validation():
    with pytest.raises(ValueError, match="edge_mm"):
        SurfaceConfig(edge_mm={"brain": 2.0})
    with pytest.raises(ValueError, match="edge_mm"):
        SurfaceConfig(edge_mm=-1.0)
    with pytest.raises(ValueError, match="taubin_mu"):
        SurfaceConfig(taubin_mu=-0.4)
    with pytest.raises(ValueError, match="remesh"):
        SurfaceConfig(remesh="poisson")
    assert SurfaceConfig(edge_mm={Tissue.BRAIN: 1, "csf": 2, "skull": 3, "SCALP": 4}).edges()[Tissue.SCALP] == 4.0


# ---------------------------------------------------------------------------------------------
# checks on hand-made meshes


def ico(radius=10.0, sub=3, centre=(0.0, 0.0, 0.0), tissue=Tissue.BRAIN):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=radius)
    return Surface(s.vertices + np.asarray(centre), s.faces, tissue)


def test_check_surface_detects_defects():
    s = ico()
    chk = check_surface(s)
    assert chk.ok and chk.self_intersections == 0
    assert chk.volume_mm3 == pytest.approx(trimesh.creation.icosphere(3, radius=10.0).volume)
    # a hole
    chk = check_surface(Surface(s.vertices, s.faces[1:], s.tissue))
    assert chk.boundary_edges == 3 and not chk.ok
    # inward
    chk = check_surface(Surface(s.vertices, s.faces[:, ::-1], s.tissue))
    assert chk.volume_mm3 < 0 and not chk.ok and chk.inconsistent_edges == 0
    # one flipped face: its three edges are traversed twice in the same direction
    f = s.faces.copy()
    f[0] = f[0, ::-1]
    assert check_surface(Surface(s.vertices, f, s.tissue)).inconsistent_edges == 3
    # two components
    b = ico(centre=(30, 0, 0))
    two = Surface(np.vstack([s.vertices, b.vertices]), np.vstack([s.faces, b.faces + len(s.vertices)]), s.tissue)
    assert check_surface(two).n_components == 2
    # two tetrahedra sharing one vertex: edge-manifold, but that vertex has two fans
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1.0]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3],
                  [0, 4, 5], [0, 6, 4], [0, 5, 6], [4, 6, 5]])
    chk = check_surface(Surface(V, F, Tissue.BRAIN))
    assert chk.nonmanifold_vertices == 1 and chk.nonmanifold_edges == 0 and chk.boundary_edges == 0


def test_tri_tri_intersect_cases():
    T = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    cases = {
        "crossing": (np.array([[0.2, 0.2, -1], [0.2, 0.2, 1], [0.3, 0.9, 0.0]]), True),
        "above": (T + [0, 0, 0.1], False),
        "beside_coplanar": (T + [1.1, 0, 0], False),
        "overlap_coplanar": (T + [0.3, 0.3, 0], True),
        "touching_point": (np.array([[1, 0, 0], [2, 0, 0], [1, 0, 1.0]]), True),
        "near_miss_edge": (np.array([[0.6, 0.6, -1], [0.6, 0.6, 1], [2, 2, 0.0]]), False),
    }
    A = np.repeat(T[None], len(cases), axis=0)
    B = np.stack([c[0] for c in cases.values()])
    got = _tri_tri_intersect(A, B)
    assert dict(zip(cases, got.tolist())) == {k: v[1] for k, v in cases.items()}


def test_self_intersections_found():
    s = ico(sub=3)
    assert len(self_intersections(s)) == 0
    # push one vertex through the sphere to the far side
    V = s.vertices.copy()
    V[0] *= -1.5
    hits = self_intersections(Surface(V, s.faces, s.tissue))
    assert len(hits) > 0
    assert not check_surface(Surface(V, s.faces, s.tissue)).ok


def test_surface_gap_analytic():
    inner, outer = ico(10.0, sub=4), ico(12.0, sub=4, tissue=Tissue.CSF)
    # vertices on the spheres; faces sag inward by at most R (1 - cos a), a the face's angular
    # circumradius (~0.036 rad at 4 subdivisions): gap in [2 - 12 (1 - cos a), 2]
    g = surface_gap_mm(inner, outer, search_mm=3.0)
    assert 2.0 - 12 * (1 - np.cos(0.04)) <= g <= 2.0 + 1e-4  # float32 inside manifold3d
    assert surface_gap_mm(inner, outer, search_mm=1.0) == pytest.approx(1.0)
    # crossing surfaces: 0
    assert surface_gap_mm(ico(10.0, centre=(3, 0, 0)), outer, search_mm=3.0) == 0.0


# ---------------------------------------------------------------------------------------------
# phantom heads (jaxhead.phantom): real head shapes, folded brain, neck


def _check_head(labels, cfg=SurfaceConfig()):
    from jaxhead.geometry.layers import make_layers_reported

    layers, lrep = make_layers_reported(labels)
    surfaces, rep = extract_surfaces_reported(layers, cfg)
    edges = cfg.edges()
    for t, s in surfaces.items():
        chk = check_surface(s)
        assert chk.ok, (t, chk.problems())
        # smoothing + remeshing keep the enclosed volume within 2% of the voxel volume
        assert rep[t].volume_mm3 == pytest.approx(rep[t].voxel_volume_mm3, rel=0.02), t
        assert rep[t].edge_mm[2] == pytest.approx(edges[t], rel=0.3), t
    for inner, outer in zip(TISSUES[:-1], TISSUES[1:]):
        assert surface_gap_mm(surfaces[inner], surfaces[outer], search_mm=1.0) >= cfg.min_gap_mm
    return layers, lrep, surfaces, rep


def test_phantom_head_coarse():
    phantom = pytest.importorskip("jaxhead.phantom")
    _, labels = phantom.make_head("ct", voxel_mm=6.0, seed=1, bias=False)
    _check_head(labels, SurfaceConfig(edge_mm=6.0))


@pytest.mark.slow
@pytest.mark.parametrize("voxel_mm", [2.0, 1.0])
def test_phantom_head(voxel_mm):
    phantom = pytest.importorskip("jaxhead.phantom")
    _, labels = phantom.make_head("mri", voxel_mm=voxel_mm, seed=0)
    layers, lrep, surfaces, rep = _check_head(labels)
    # the phantom's ventricles are CSF inside the brain: filled into the brain and counted
    assert lrep.ventricle_voxels > 0
    assert lrep.changes["ventricles"] == {(Tissue.CSF, Tissue.BRAIN): lrep.ventricle_voxels}


#: A 9-voxel box of the layered CSF solid of the MNI152-based head at 1 mm segmented with the
#: ANTs atlas (experiments/mni152_chain.py --heldout), around the place where the CSF surface got
#: a handle: a one-voxel skull spike into the CSF. np.packbits of the (9, 9, 9) bool mask.
HANDLE_BOX = bytes.fromhex(
    "000000000000000100fc0000000000000100ee7fc00000000000008c7e3fe000000000001c647ffff0000000003c"
    "0fbffffff80000007820bffffffffc0000383dfffffffffffe80345e3fffffffffffff6073fdffffffffffffff80")


def test_marching_cubes_prefers_the_presmoothing_whose_surface_is_a_sphere():
    box = np.unpackbits(np.frombuffer(HANDLE_BOX, np.uint8))[:729].reshape(9, 9, 9).astype(bool)
    pad = np.pad(box, 3)
    _, F = surface_module._marching_cubes(pad, np.eye(4), 0.5)
    assert euler_number(F) == 0  # the configured presmoothing's level set has a handle
    V, F, sigma = surface_module._sphere_marching_cubes(pad, np.eye(4), 0.5, Tissue.CSF)
    assert euler_number(F) == 2 and sigma == 0.75
    # a ball keeps the configured sigma; a thick voxel torus (no sphere at any sigma) keeps its
    # own surface and the configured sigma
    g = np.arange(-12, 13)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    ball = X**2 + Y**2 + Z**2 <= 64
    _, F, sigma = surface_module._sphere_marching_cubes(ball, np.eye(4), 0.5, Tissue.BRAIN)
    assert euler_number(F) == 2 and sigma == 0.5
    torus = (np.hypot(X, Y) - 7) ** 2 + Z**2 <= 9
    _, F, sigma = surface_module._sphere_marching_cubes(torus, np.eye(4), 0.5, Tissue.BRAIN)
    assert euler_number(F) == 0 and sigma == 0.5
    assert euler_number(trimesh.creation.icosphere(2).faces) == 2
