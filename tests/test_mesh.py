"""tetrahedralize on nested spheres with each mesher: labels, orientation, interfaces, volumes,
Table-2 quality, refinement, errors; surface refinement and region seeds."""

import importlib

import numpy as np
import pytest
import trimesh

from jaxhead.geometry import MeshConfig, TetMesh, enclosed_volume, tetrahedralize, tetrahedralize_reported
from jaxhead.geometry.refine import refine_surface
from jaxhead.geometry.surface import Surface
from jaxhead.tissue import TISSUES, Tissue

# `jaxhead.geometry.tetrahedralize` is also the function's name in the package: import the module.
T = importlib.import_module("jaxhead.geometry.tetrahedralize")

#: Each mesher backend and the package it needs (optional ones are skipped when not installed).
BACKENDS = {"gmsh": "gmsh", "tetgen": "tetgen", "ftetwild": "pytetwild"}

RADII = (8.0, 10.0, 12.0, 14.0)  # mm: a brain of 8 mm and three 2 mm shells
SUBDIV = 3  # icosphere edges ~0.15 R: 1.2 mm (brain) to 2.2 mm (scalp)
REFINE_AT = np.array([[RADII[3], 0.0, 0.0]])


def _sphere(r, subdiv=SUBDIV):
    s = trimesh.creation.icosphere(subdivisions=subdiv, radius=r)
    return np.asarray(s.vertices), np.asarray(s.faces)


def _surfaces(radii=RADII, subdiv=SUBDIV):
    return {t: Surface(*_sphere(r, subdiv), t) for t, r in zip(TISSUES, radii)}


def _sagitta(r, subdiv=SUBDIV):
    """Largest distance between the icosphere and its sphere: (circumradius of a face)^2 / (2 R)."""
    v, f = _sphere(r, subdiv)
    e = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).max()
    return (e / np.sqrt(3)) ** 2 / (2 * r)


@pytest.fixture(scope="module", params=list(BACKENDS))
def meshed(request):
    pytest.importorskip(BACKENDS[request.param])
    cfg = MeshConfig(mesher=request.param, edge_mm=4.0, refine_points_mm=REFINE_AT,
                     refine_radius_mm=4.0, refine_edge_mm=1.0, threads=1, stop_energy=30.0,
                     max_opt_iterations=10)  # a quick fTetWild; the improvement step does the rest
    mesh, rep = tetrahedralize_reported(_surfaces(), cfg)
    assert rep.mesher == request.param
    return mesh, rep


def _faces_closed_oriented(faces):
    """Every directed edge once and its reverse once: closed, manifold, consistently oriented."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    return len(fwd) == len(e) and all((b, a) in fwd for a, b in fwd)


def _area(nodes, faces):
    p = nodes[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()


def test_mesh_is_valid_positive_and_labelled(meshed):
    mesh, rep = meshed
    assert isinstance(mesh, TetMesh)
    assert np.all(mesh.tet_volumes() > 0)  # TetMesh also checks this
    assert set(np.unique(mesh.labels)) == {1, 2, 3, 4}
    assert 1000 < mesh.n_tets < 100_000
    # Every tet's centroid lies in its own shell, up to the band where the polyhedral surface
    # (inside the sphere by at most the sagitta) and fTetWild's envelope make the side ambiguous.
    r = np.linalg.norm(mesh.centroids(), axis=1)
    band = [_sagitta(R) + rep.envelope_mm for R in RADII]
    for k, t in enumerate(TISSUES):
        inner = RADII[k - 1] + rep.envelope_mm if k else -1.0
        sure = (r > inner) & (r < RADII[k] - band[k])
        assert sure.sum() > 50
        assert np.all(mesh.labels[sure] == int(t)), t
    outside = r > RADII[3] + rep.envelope_mm
    assert not outside.any()  # nothing outside the scalp surface


def test_labels_match_winding_numbers(meshed):
    """Each tet's label is the tissue its centroid's winding numbers give (inside k surfaces:
    tissue 5 - k). gmsh and TetGen keep the input triangles, so this holds for every tet; fTetWild
    inserts them within its envelope, so only tets whose centroid is farther than the envelope
    from every surface are decided by their centroid."""
    mesh, rep = meshed
    surfs = [(s.vertices, s.faces) for s in _surfaces().values()]
    c = mesh.centroids()
    n_in = T._inside_count(surfs, c)
    assert np.all(n_in >= 1)  # nothing outside the scalp surface
    by_winding = 5 - n_in
    if rep.mesher == "ftetwild":
        d = np.min([T._Dist(V, F)(c) for V, F in surfs], axis=0)
        sure = d > 1.01 * rep.envelope_mm
        assert sure.mean() > 0.9
        assert np.array_equal(by_winding[sure], mesh.labels[sure])
    else:
        assert rep.envelope_mm == 0.0 and rep.relabelled_near_interface == 0
        assert np.array_equal(by_winding, mesh.labels)


def _mesh_sagitta(mesh, k):
    """Chord sagitta of the meshed interface k (BRAIN..SCALP) on its sphere: (circumradius of its
    largest face)^2 / (2 R). The improvement slides interface nodes along the polyhedral input
    surface, so the meshed faces are chords between points of it, not its own triangles."""
    if k == 3:
        f = mesh.boundary_faces()[0]
    else:
        f = mesh.interface_faces(TISSUES[k], TISSUES[k + 1])
    e = np.linalg.norm(mesh.nodes[f] - mesh.nodes[np.roll(f, 1, axis=1)], axis=2).max()
    return (e / np.sqrt(3)) ** 2 / (2 * RADII[k])


def test_volumes_match_surfaces_and_spheres(meshed):
    mesh, rep = meshed
    vols = mesh.tissue_volumes_mm3()
    # Both the polyhedral input surface k and the meshed interface k lie between the sphere and
    # the sphere less (input sagitta + mesh chord sagitta + envelope): fTetWild keeps interfaces
    # within its envelope of the input, gmsh and TetGen keep the input triangles (envelope 0) and
    # the improvement slides nodes along them. So a shell's volume differs from the polyhedra's
    # by at most (area of its two surfaces) x that band, and from the analytic shell likewise.
    band = [_sagitta(R) + _mesh_sagitta(mesh, k) + rep.envelope_mm for k, R in enumerate(RADII)]
    exact = np.diff([0.0] + [4 / 3 * np.pi * R**3 for R in RADII])
    for k, t in enumerate(TISSUES):
        bound = sum(4 * np.pi * RADII[j] ** 2 * band[j] for j in (k - 1, k) if j >= 0)
        assert abs(vols[t] - rep.surface_volume_mm3[t]) <= bound, t
        assert abs(vols[t] - exact[k]) <= bound, t
        # The bound is loose (chords of 4 mm faces: 8-17 % of a 2 mm shell); the error is small.
        assert abs(vols[t] / exact[k] - 1) < 0.03, t
    assert sum(vols.values()) == pytest.approx(mesh.tet_volumes().sum())


def test_boundary_is_closed_sphere(meshed):
    mesh, rep = meshed
    faces, owner = mesh.boundary_faces()
    assert _faces_closed_oriented(faces)
    assert np.all(mesh.labels[owner] == Tissue.SCALP)
    # Outward: the enclosed volume by the divergence theorem is the mesh volume.
    p = mesh.nodes[faces]
    enclosed = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6
    assert enclosed == pytest.approx(mesh.tet_volumes().sum(), rel=1e-9)
    # Area of the polyhedral scalp surface (its faces are kept within the envelope), and of the
    # sphere up to the chord deficit (<= 2 s / R relative, for sagitta s).
    s = _surfaces()[Tissue.SCALP]
    assert _area(mesh.nodes, faces) == pytest.approx(_area(s.vertices, s.faces), rel=0.01)
    R = RADII[3]
    assert _area(mesh.nodes, faces) == pytest.approx(4 * np.pi * R**2, rel=2 * _sagitta(R) / R + 0.01)
    assert rep.interface_max_dev_mm[Tissue.SCALP] <= 1.01 * rep.envelope_mm + 1e-9


def test_interfaces_are_closed_surfaces_on_their_spheres(meshed):
    mesh, rep = meshed
    for k in range(3):
        inner, outer = TISSUES[k], TISSUES[k + 1]
        f = mesh.interface_faces(inner, outer)
        assert len(f) > 0
        assert _faces_closed_oriented(f), inner
        # Only adjacent tissues touch (no BRAIN-SKULL faces): the shells are closed.
        for far in TISSUES[k + 2:]:
            assert len(mesh.interface_faces(inner, far)) == 0
        # The interface lies on its input surface (within the envelope; relocated nodes exactly).
        r = np.linalg.norm(mesh.nodes[np.unique(f)], axis=1)
        assert r.max() <= RADII[k] + 1e-9
        assert r.min() >= RADII[k] - _sagitta(RADII[k]) - rep.envelope_mm
        assert rep.interface_max_dev_mm[inner] <= 1.01 * rep.envelope_mm + 1e-9  # (rounding)


def test_quality_after_improvement(meshed):
    from jaxhead.geometry.quality import tet_metrics

    mesh, rep = meshed
    q = tet_metrics(mesh.nodes, mesh.tets)
    assert np.all(np.asarray(q["jacobian"]) > 0)
    # The seed paper's limits: scaled Jacobian >= 0.2, condition number <= 3.
    assert np.all(np.asarray(q["scaled_jacobian"]) >= 0.2)
    assert np.all(np.asarray(q["condition"]) <= 3)
    assert rep.improvement["below_0.2_after"] == 0


def test_refinement_near_points(meshed):
    mesh, _ = meshed
    c = mesh.centroids()
    h = np.cbrt(mesh.tet_volumes())
    near = np.linalg.norm(c - REFINE_AT[0], axis=1) < 3.0
    far = np.linalg.norm(c + REFINE_AT[0], axis=1) < 3.0  # the opposite side of the scalp
    assert near.sum() > 10 and far.sum() > 3
    # Target edges 1 mm near vs ~2-4 mm far: tets there are markedly smaller.
    assert np.median(h[near]) < 0.7 * np.median(h[far])


def test_missing_tissue_raises():
    s = _surfaces()
    del s[Tissue.SKULL]
    with pytest.raises(ValueError, match="SKULL"):
        tetrahedralize(s)


def test_wrong_key_raises():
    s = _surfaces()
    s[Tissue.CSF], s[Tissue.SKULL] = s[Tissue.SKULL], s[Tissue.CSF]
    with pytest.raises(ValueError, match="key each surface by its own tissue"):
        tetrahedralize(s)


def test_not_nested_raises():
    s = _surfaces(radii=(8.0, 12.0, 10.0, 14.0))
    with pytest.raises(ValueError, match="CSF surface is not inside the SKULL"):
        tetrahedralize(s)


def test_open_surface_raises():
    s = _surfaces()
    v, f = s[Tissue.CSF].vertices, s[Tissue.CSF].faces
    s[Tissue.CSF] = Surface(v, f[1:], Tissue.CSF)
    with pytest.raises(ValueError, match="CSF surface is not a closed"):
        tetrahedralize(s)


def test_inward_surface_raises():
    s = _surfaces()
    v, f = s[Tissue.BRAIN].vertices, s[Tissue.BRAIN].faces
    s[Tissue.BRAIN] = Surface(v, f[:, ::-1], Tissue.BRAIN)
    with pytest.raises(ValueError, match="BRAIN surface encloses volume"):
        tetrahedralize(s)


def test_envelope_too_large_raises():
    pytest.importorskip("pytetwild")
    with pytest.raises(ValueError, match="envelope_mm"):
        tetrahedralize(_surfaces(), MeshConfig(mesher="ftetwild", envelope_mm=1.5))


def test_mesher_choice(monkeypatch):
    """"auto" takes the first installed of gmsh, TetGen, fTetWild; a named mesher that is not
    installed raises, naming the argument and how to install it."""
    have = T.available_meshers()
    assert have == tuple(m for m in T.MESHERS if m in have)
    if have:
        assert T.choose_mesher("auto") == have[0]
    monkeypatch.setattr(T, "available_meshers", lambda: ("ftetwild",))
    assert T.choose_mesher("auto") == "ftetwild"
    with pytest.raises(ValueError, match=r"`mesher` = 'gmsh'.*jaxhead\[gmsh\]"):
        T.choose_mesher("gmsh")
    with pytest.raises(ValueError, match=r"`mesher` = 'tetgen'.*jaxhead\[tetgen\]"):
        tetrahedralize(_surfaces(), MeshConfig(mesher="tetgen"))
    monkeypatch.setattr(T, "available_meshers", lambda: ())
    with pytest.raises(ValueError, match="none of gmsh, tetgen, pytetwild is installed"):
        T.choose_mesher("auto")


@pytest.mark.parametrize("mesher", ["gmsh", "tetgen"])
def test_constrained_delaunay_meshers_are_deterministic(mesher):
    """gmsh (HXT, fixed thread count) and TetGen give the same mesh twice (fTetWild does not:
    wildmeshing/fTetWild#72); the input vertices come first, unmoved."""
    pytest.importorskip(BACKENDS[mesher])
    cfg = MeshConfig(mesher=mesher, edge_mm=3.0, threads=2, improve="none")
    s = _surfaces(subdiv=2)
    a, b = tetrahedralize(s, cfg), tetrahedralize(s, cfg)
    assert np.array_equal(a.nodes, b.nodes) and np.array_equal(a.tets, b.tets)
    assert np.array_equal(a.labels, b.labels)
    V = np.concatenate([x.vertices for x in s.values()])
    np.testing.assert_array_equal(a.nodes[:len(V)], V)


def _min_angle_deg(V, F):
    p = V[F]
    out = []
    for i in range(3):
        u, v = p[:, (i + 1) % 3] - p[:, i], p[:, (i + 2) % 3] - p[:, i]
        cos = np.einsum("ij,ij->i", u, v) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
        out.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.min(out)


def test_refine_surface_bisects_near_points_only():
    """Longest-edge bisection: the same polyhedron (enclosed volume to rounding, closed and
    oriented), every edge at most 1.5 x the target, untouched far away, and angles at least half
    the input's (Rivara 1997: longest-edge bisection at most halves the smallest angle once)."""
    V, F = _sphere(RADII[3])
    p = REFINE_AT[0]

    def size(x):
        return 0.5 + 0.5 * np.maximum(np.linalg.norm(x - p, axis=1) - 3.0, 0.0)

    V2, F2, n = refine_surface(V, F, size)
    assert n > 0 and len(F2) == len(F) + 2 * n and len(V2) == len(V) + n
    np.testing.assert_array_equal(V2[:len(V)], V)
    assert _faces_closed_oriented(F2)
    assert enclosed_volume(V2, F2) == pytest.approx(enclosed_volume(V, F), rel=1e-12)
    e = np.sort(np.stack([F2, np.roll(F2, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    e = np.unique(e, axis=0)
    mid = 0.5 * (V2[e[:, 0]] + V2[e[:, 1]])
    length = np.linalg.norm(V2[e[:, 0]] - V2[e[:, 1]], axis=1)
    assert np.all(length <= 1.5 * size(mid) + 1e-12)
    far = np.linalg.norm(V[F].mean(axis=1) - p, axis=1) > 12.0  # where the target exceeds every edge
    kept = {tuple(f) for f in F2.tolist()}
    assert all(tuple(f) in kept for f in F[far].tolist())
    assert _min_angle_deg(V2, F2) >= _min_angle_deg(V, F) / 2 - 1e-9
    # Nothing to do: the input comes back unchanged.
    V3, F3, n3 = refine_surface(V, F, lambda x: np.full(len(x), np.inf))
    assert n3 == 0 and np.array_equal(F3, F)


def test_region_seeds_lie_in_their_shells():
    surfs = [(s.vertices, s.faces) for s in _surfaces().values()]
    seeds = T.region_seeds(surfs)
    r = np.linalg.norm(seeds, axis=1)
    # Inside polyhedron k (itself inside sphere k); outside polyhedron k - 1 (which lies between
    # the sphere and the sphere less the sagitta).
    inner = np.array([0.0] + [R - _sagitta(R) for R in RADII[:3]])
    assert np.all(r > inner) and np.all(r < np.array(RADII))
    assert np.array_equal(5 - T._inside_count(surfs, seeds), [int(t) for t in TISSUES])


@pytest.mark.parametrize("kw, match", [
    (dict(edge_mm=-1.0), "edge_mm"),
    (dict(edge_mm={"brain": 2.0}), "lacks"),
    (dict(edge_mm={"bone": 2.0}), "bone"),
    (dict(refine_points_mm=[[1.0, 2.0]]), "refine_points_mm"),
    (dict(stop_energy=2.0), "stop_energy"),
    (dict(improve="mmg"), "improve"),
    (dict(mesher="mmg"), "mesher"),
    (dict(threads=-1), "threads"),
])
def test_config_validation(kw, match):
    with pytest.raises(ValueError, match=match):
        MeshConfig(**kw)


def test_config_accepts_names_and_tissues():
    a = MeshConfig(edge_mm={"brain": 3, "csf": 1.5, "skull": 2, "scalp": 2.5}).edges()
    b = MeshConfig(edge_mm={Tissue.BRAIN: 3, Tissue.CSF: 1.5, Tissue.SKULL: 2, Tissue.SCALP: 2.5}).edges()
    assert a == b and a[Tissue.CSF] == 1.5
    assert MeshConfig(refine_points_mm=np.zeros((2, 3))).refine_points_mm == ((0.0,) * 3,) * 2


@pytest.mark.slow
def test_phantom_head_mesh():
    """A 2 mm phantom head meshed as the pipeline's mesh stage does (refined under the 10-20
    electrodes): four tissues, Table-2 clean, volumes and labels near the voxels, and the scalp
    tets under the electrodes markedly smaller than elsewhere."""
    from scipy.spatial import cKDTree

    from jaxhead.electrodes import ElectrodeConfig, refined_mesh_config
    from jaxhead.phantom import make_head
    from jaxhead.geometry.quality import quality_report
    from jaxhead.geometry.layers import make_layers
    from jaxhead.geometry.surface import extract_surfaces
    from jaxhead.tissue import Tissue
    from jaxhead.volume import voxel_sizes

    _, labels = make_head("mri", voxel_mm=2.0)
    layers = make_layers(labels)
    surfaces = extract_surfaces(layers)
    cfg = refined_mesh_config(MeshConfig(), surfaces[Tissue.SCALP], ElectrodeConfig())
    assert len(cfg.refine_points_mm) == 21
    mesh, rep = tetrahedralize_reported(surfaces, cfg)
    # Refinement: scalp tets within the refine radius of an electrode have a mean edge near the
    # 2 mm target; the rest of the scalp grades up to its 6 mm edge.
    scalp = mesh.labels == int(Tissue.SCALP)
    p = mesh.nodes[mesh.tets[scalp]]
    edge = np.mean([np.linalg.norm(p[:, i] - p[:, j], axis=1) for i in range(4) for j in range(i + 1, 4)],
                   axis=0)
    d, _ = cKDTree(np.asarray(cfg.refine_points_mm)).query(p.mean(axis=1))
    near, far = edge[d <= cfg.refine_radius_mm].mean(), edge[d > 2 * cfg.refine_radius_mm].mean()
    assert near < 1.5 * cfg.refine_edge_mm and near < 0.6 * far, (near, far)
    row = quality_report(mesh).table2_row
    assert row["jacobian"] == 0 and row["scaled_jacobian"] == 0 and row["condition"] == 0
    lab = np.asarray(layers.labels)
    vox = float(np.prod(voxel_sizes(np.asarray(layers.affine))))
    for t, v in mesh.tissue_volumes_mm3().items():
        # Surfaces are smoothed marching-cubes level sets of 2 mm voxels: a shell's volume moves
        # by about (its surfaces' area) x (a fraction of a voxel); 5 % covers the thin CSF.
        assert v == pytest.approx((lab == int(t)).sum() * vox, rel=0.05), t
    inv = np.linalg.inv(np.asarray(layers.affine))
    ijk = np.rint(mesh.centroids() @ inv[:3, :3].T + inv[:3, 3]).astype(int)
    agree = np.mean(lab[tuple(ijk.T)] == mesh.labels)
    assert agree > 0.95  # boundary voxels are a large fraction at 2 mm
    for t in TISSUES:
        assert rep.interface_max_dev_mm[t] <= 1.01 * rep.envelope_mm + 1e-9  # gmsh: 0 up to rounding


def test_flat_tet_at_interface_takes_its_neighbours_side():
    """A flat tet whose centroid lies just outside the BRAIN surface, but inside the envelope,
    and whose other faces touch brain tets, is BRAIN (fTetWild's interface is its outer face)."""
    from jaxhead.geometry.tetrahedralize import _Dist, label_tets

    s = _surfaces(subdiv=4)
    surfs = [(s[t].vertices, s[t].faces) for t in TISSUES]
    dists = [_Dist(*x) for x in surfs]
    env = 0.1
    v, f = surfs[0]
    p = v[f[0]]
    centre = p.mean(axis=0)
    n = np.cross(p[1] - p[0], p[2] - p[0])
    n /= np.linalg.norm(n)  # outward (faces are counter-clockwise seen from outside)
    tang = (p - centre) * 0.3  # a small triangle within the face's plane
    a, b, c = centre + tang + 0.9 * env * n  # just outside, within the envelope
    inner = centre - 2.0 * env * n
    deep = [centre - 8.0 * env * n + t for t in tang]
    nodes = np.array([a, b, c, inner, *deep])
    tets = np.array([[0, 1, 2, 3],  # the flat tet: centroid 0.175 env outside
                     [0, 1, 3, 4], [1, 2, 3, 5], [2, 0, 3, 6]])  # brain tets on its inner faces
    centroid_out = dists[0](nodes[tets[:1]].mean(axis=1))[0]
    assert 0 < centroid_out < env
    labels, n_relabelled, conflicts = label_tets(nodes, tets, surfs, dists, env)
    assert labels.tolist() == [1, 1, 1, 1]
    assert n_relabelled == 1 and conflicts == 0
    # Without the envelope (a surface known exactly), the centroid decides: CSF.
    labels0, n0, _ = label_tets(nodes, tets, surfs, dists, 1e-6)
    assert labels0[0] == int(Tissue.CSF) and n0 == 0


def test_ftetwild_leaves_the_working_directory_clean(tmp_path, monkeypatch):
    """fTetWild writes "__tracked_surface.stl" into the working directory; the user's folder stays clean."""
    pytest.importorskip("pytetwild")
    monkeypatch.chdir(tmp_path)
    V, F = _sphere(10.0, subdiv=2)
    nodes, tets = T._pytetwild(V, F.astype(np.int32), edge_length_abs=5.0, epsilon=1e-2,
                               optimize=False, quiet=True, num_threads=1)
    assert len(tets) > 0
    assert list(tmp_path.iterdir()) == []


def test_default_gmsh_mesh_is_repeatable():
    """The default (one mesher thread) gives the same mesh on every run. With threads=0 (both cores)
    gmsh's parallel HXT refinement gave 108,678 / 108,621 / 108,678 tets on these spheres in three
    runs, so this fails there about two times in three."""
    pytest.importorskip("gmsh")
    surfaces = {t: Surface(*_sphere(r, 4), t) for t, r in zip(TISSUES, (40.0, 45.0, 50.0, 55.0))}
    refine = trimesh.creation.icosphere(subdivisions=1, radius=55.0).vertices[:12]
    cfg = MeshConfig(mesher="gmsh", edge_mm=3.0, refine_points_mm=refine, refine_radius_mm=8.0,
                     refine_edge_mm=1.5)
    a, b = tetrahedralize(surfaces, cfg), tetrahedralize(surfaces, cfg)
    assert a.tets.shape == b.tets.shape
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_array_equal(a.nodes, b.nodes)
    np.testing.assert_array_equal(a.labels, b.labels)
