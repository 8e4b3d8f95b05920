"""Mesh improvement: 2-3 / 3-2 flips and edge splits keep tissues and interfaces, take the better
configuration, and the sizing field follows the surfaces' own edges."""

import numpy as np
import pytest
import trimesh

from jaxhead.geometry.improve import _flip_pass, _split_pass, tet_quality
from jaxhead.geometry.tetrahedralize import (
    _SURFACE_EDGE_FACTOR,
    _SURFACE_GRADING,
    MeshConfig,
    face_adjacency,
    _vertex_edge_mm,
    signed_volumes,
    sizing_field,
    tetrahedralize,
)
from jaxhead.geometry.surface import Surface
from jaxhead.tissue import TISSUES, Tissue


def _bipyramid(h):
    """Equilateral triangle (side 1) in z = 0 and apexes at +-h above its centroid."""
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(3) / 2, 0.0]])
    c = a.mean(axis=0)
    nodes = np.vstack([a, c + [0, 0, h], c - [0, 0, h]])
    two = np.array([[0, 1, 2, 3], [0, 2, 1, 4]])
    three = np.array([[0, 1, 4, 3], [1, 2, 4, 3], [2, 0, 4, 3]])
    return nodes, two, three


def _faces(tets, labels):
    """Boundary faces and faces between different labels, as sets of sorted node triples."""
    faces, owner, i, j, boundary = face_adjacency(tets)
    key = lambda f: {tuple(sorted(x)) for x in f.tolist()}  # noqa: E731
    iface = labels[owner[i]] != labels[owner[j]]
    return key(faces[boundary]), key(faces[i[iface]])


def _conforming(tets):
    """Every face shared by at most two tets."""
    k = np.sort(tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(k, axis=0, return_counts=True)
    return counts.max() <= 2


def test_bipyramid_orientations():
    nodes, two, three = _bipyramid(0.8)
    assert np.all(signed_volumes(nodes, two) > 0)
    assert np.all(signed_volumes(nodes, three) > 0)
    assert signed_volumes(nodes, two).sum() == pytest.approx(signed_volumes(nodes, three).sum())


@pytest.mark.parametrize("h", [0.05, 0.2, 0.5, 0.8, 1.5, 3.0])
def test_flips_take_the_better_of_two_and_three_tets(h):
    """From either configuration of the bipyramid, one pass ends in the one with the better worst
    tet (compared here directly), with the same volume and the same outer faces."""
    nodes, two, three = _bipyramid(h)
    better = "two" if tet_quality(nodes, two).min() > tet_quality(nodes, three).min() else "three"
    for name, tets in (("two", two), ("three", three)):
        labels = np.full(len(tets), 2)
        q = tet_quality(nodes, tets)
        out, lab, q_out, n23, n32 = _flip_pass(nodes, tets, labels, q, target=1.0)
        assert len(out) == len(two if better == "two" else three), (name, h)
        assert (n23, n32) == ((1, 0) if (name, better) == ("two", "three") else
                              (0, 1) if (name, better) == ("three", "two") else (0, 0))
        assert np.all(signed_volumes(nodes, out) > 0)
        assert signed_volumes(nodes, out).sum() == pytest.approx(signed_volumes(nodes, tets).sum())
        assert _faces(out, lab)[0] == _faces(tets, labels)[0]
        np.testing.assert_allclose(q_out, tet_quality(nodes, out))
        assert np.all(lab == 2)


def test_flips_never_cross_tissues():
    """The same bipyramid with its tets in two tissues: no flip (it would move the interface)."""
    for h in (0.05, 3.0):
        nodes, two, three = _bipyramid(h)
        for tets, labels in ((two, np.array([1, 2])), (three, np.array([1, 1, 2]))):
            out, lab, _, n23, n32 = _flip_pass(nodes, tets, labels, tet_quality(nodes, tets), 1.0)
            assert (n23, n32) == (0, 0) and np.array_equal(out, tets)


def test_split_of_an_interior_edge():
    """Six needles around a long axis (a closed ring): the axis is split at its midpoint, each tet
    into two; volume and outer faces stay (relocation then shapes the tets around the new node)."""
    k = 6
    ang = 2 * np.pi * np.arange(k) / k
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(k)], axis=1)
    nodes = np.vstack([ring, [[0, 0, 4.0], [0, 0, -4.0]]])
    tets = np.array([[k + 1, k, i, (i + 1) % k] for i in range(k)])
    from jaxhead.geometry import orient_tets

    tets, _ = orient_tets(nodes, tets)
    labels = np.full(k, 3)
    q = tet_quality(nodes, tets)
    n2, t2, l2, q2, n_split = _split_pass(nodes, tets, labels, q, target=1.0)
    assert n_split == 1 and len(t2) == 2 * k and len(n2) == k + 3
    np.testing.assert_allclose(n2[-1], [0, 0, 0])  # the axis's midpoint
    assert np.all(signed_volumes(n2, t2) > 0)
    assert signed_volumes(n2, t2).sum() == pytest.approx(signed_volumes(nodes, tets).sum())
    assert _faces(t2, l2)[0] == _faces(tets, labels)[0]
    np.testing.assert_allclose(q2, tet_quality(n2, t2))


def test_split_skips_open_rings():
    """A boundary edge (open ring) is never split: its midpoint would dent the boundary."""
    nodes, two, _ = _bipyramid(3.0)
    labels = np.array([1, 1])
    out = _split_pass(nodes, two, labels, tet_quality(nodes, two), target=1.0)
    assert out[-1] == 0


def _spheres(radii=(8.0, 10.0, 12.0, 14.0), subdiv=3):
    return {t: Surface(*map(np.asarray, (lambda s: (s.vertices, s.faces))(
        trimesh.creation.icosphere(subdivisions=subdiv, radius=r))), t) for t, r in zip(TISSUES, radii)}


@pytest.fixture(scope="module")
def raw_mesh():
    """fTetWild's labelled sphere mesh without improvement (some tets below the target)."""
    pytest.importorskip("pytetwild")
    cfg = MeshConfig(mesher="ftetwild", edge_mm=4.0, threads=1, stop_energy=30.0, max_opt_iterations=5,
                     improve="none")
    m = tetrahedralize(_spheres(), cfg)
    return np.asarray(m.nodes), np.asarray(m.tets), np.asarray(m.labels)


def test_passes_keep_tissues_and_interfaces_on_a_mesh(raw_mesh):
    """Flips and splits at a high target (most tets 'poor'): the tissue volumes, the boundary and
    every interface face are exactly those of the input; the mesh stays conforming and positive."""
    nodes, tets, labels = raw_mesh
    vol = {t: signed_volumes(nodes, tets[labels == int(t)]).sum() for t in TISSUES}
    faces = _faces(tets, labels)
    q = tet_quality(nodes, tets)
    t1, l1, q1, n23, n32 = _flip_pass(nodes, tets, labels, q, target=0.5)
    assert n23 + n32 > 0  # (3-2 flips are rare in fTetWild meshes; the bipyramid tests them)
    assert len(t1) == len(tets) + n23 - n32
    n2, t2, l2, q2, n_split = _split_pass(nodes, t1, l1, q1, target=0.5)
    assert n_split > 0
    for n_, t_, l_, q_ in ((nodes, t1, l1, q1), (n2, t2, l2, q2)):
        assert np.all(signed_volumes(n_, t_) > 0)
        assert _conforming(t_)
        assert _faces(t_, l_) == faces
        np.testing.assert_allclose(q_, tet_quality(n_, t_))
        for t in TISSUES:
            assert signed_volumes(n_, t_[l_ == int(t)]).sum() == pytest.approx(vol[t], rel=1e-12)
    # Flips only take gains: the worst tet of the mesh never gets worse.
    assert q1.min() >= q.min()


def test_sizing_field_follows_surface_edges():
    """Near a surface finer than the tissue's edge, the target edge is at most 1.5 x the surface's
    own edge plus the grading times the distance (checked against every vertex, brute force)."""
    surfs = [(s.vertices, s.faces) for s in _spheres(subdiv=3).values()]
    cfg = MeshConfig(edge_mm=6.0)
    pts, _, h = sizing_field(surfs, cfg, spacing_mm=1.0)
    assert h.max() > 6.0  # outside the head: coarser
    r = np.linalg.norm(pts, axis=1)
    sample = np.random.default_rng(0).permutation(np.nonzero(r < 16.0)[0])[:3000]
    pts, h = pts[sample], h[sample]
    for V, F in surfs:
        e = _vertex_edge_mm(V, F)
        near = np.linalg.norm(pts[:, None] - V[None], axis=2)
        d_min = near.min(axis=1)
        close = d_min < 1.0
        bound = (_SURFACE_EDGE_FACTOR * e[near.argmin(axis=1)] + _SURFACE_GRADING * d_min)[close]
        assert np.all(h[close] <= bound + 1e-12)
        assert np.all(h[close] < 6.0)
    # Per-vertex mean edge, against trimesh's unique edges.
    V, F = surfs[0]
    mesh = trimesh.Trimesh(V, F, process=False)
    length = mesh.edges_unique_length
    total = np.bincount(mesh.edges_unique.ravel(), weights=np.repeat(length, 2), minlength=len(V))
    counts = np.bincount(mesh.edges_unique.ravel(), minlength=len(V))
    np.testing.assert_allclose(_vertex_edge_mm(V, F), total / counts)


def test_improve_mesh_never_worse_and_keeps_interfaces(raw_mesh):
    """The whole improvement on fTetWild's raw sphere mesh: no more tets below the Table-2 limit
    and no lower worst quality than the input; labels' tissues kept; every interface node on
    its input surface as far as it was (relocated ones exactly), and the boundary node set kept."""
    from jaxhead.geometry.improve import LIMIT, classify_nodes, improve_mesh
    from jaxhead.geometry.tetrahedralize import _check_surfaces, _Dist

    nodes, tets, labels = raw_mesh
    dists = [_Dist(V, F) for V, F in _check_surfaces(_spheres())]
    n2, t2, l2, stats = improve_mesh(nodes, tets, labels, [d.project for d in dists], iterations=10)
    q0, q2 = tet_quality(nodes, tets), tet_quality(n2, t2)
    assert stats["below_0.2_before"] == (q0 < LIMIT).sum() and stats["below_0.2_after"] == (q2 < LIMIT).sum()
    assert (q2 < LIMIT).sum() <= (q0 < LIMIT).sum() and q2.min() >= q0.min()
    assert np.all(signed_volumes(n2, t2) > 0) and _conforming(t2)
    assert set(np.unique(l2)) == set(np.unique(labels))
    c0, c2 = classify_nodes(tets, labels, len(nodes)), classify_nodes(t2, l2, len(n2))
    assert np.array_equal(c2[:len(nodes)], c0)  # split midpoints are appended, inside one tissue
    assert np.all(c2[len(nodes):] == -1)
    for k, d in enumerate(dists):
        on = np.nonzero(c0 == k)[0]
        moved = np.linalg.norm(n2[on] - nodes[on], axis=1) > 0
        assert np.all(d(n2[on][moved]) < 1e-9)
        assert d(n2[on]).max() <= d(nodes[on]).max() + 1e-12
    # Faces of the boundary and between tissues stay, by node (relocation moves nodes, not faces).
    assert _faces(t2, l2) == _faces(tets, labels)


# ---------------------------------------------------------------------------------------------
# Circumcentre insertion (the demo MRI mesh's needle fan)

#: 1045 tets cut from the demo MRI head's raw gmsh mesh (electrode-refined surfaces, 2 mm; within
#: 14 mm of a brain-surface node whose CSF-side star is a fan of 50 tets with edges up to 12 mm,
#: reaching a finely refined CSF surface 6.5 mm away): 75 tets below q = 0.2. Relocation, flips
#: and edge splits left 57 of them (52 in the whole head: the 56 of `make demo`'s Table 2).
NEEDLE_FAN = __import__("pathlib").Path(__file__).resolve().parent / "data" / "needle_fan_demo_mri.npz"


def _needle_fan():
    z = np.load(NEEDLE_FAN)
    return z["nodes"].astype(float), z["tets"].astype(np.int64), z["labels"].astype(np.int64)


def _interface_projectors(nodes, tets, labels):
    """Closest point on the mesh's own meshed surface k (and, for k = 3, its cut boundary)."""
    import gpytoolbox

    faces, owner, i, j, boundary = face_adjacency(tets)
    out = []
    for k in range(4):
        sel = faces[i[(labels[owner[i]] <= k + 1) != (labels[owner[j]] <= k + 1)]]
        if k == 3:
            sel = np.concatenate([sel, faces[boundary]])
        F = np.ascontiguousarray(sel, dtype=np.int32)

        def project(Q, F=F):
            if len(Q) == 0 or len(F) == 0:
                return np.asarray(Q)
            _, idx, lam = gpytoolbox.squared_distance(np.ascontiguousarray(Q, dtype=float), nodes, F,
                                                      use_cpp=True)
            return np.einsum("ij,ijk->ik", lam, nodes[F[idx]])

        out.append(project)
    return out


def test_circumspheres_are_equidistant():
    from jaxhead.geometry.improve import _circumspheres

    rng = np.random.default_rng(0)
    nodes = rng.normal(size=(40, 3))
    tets = np.array([rng.choice(40, 4, replace=False) for _ in range(30)])
    c, r2 = _circumspheres(nodes, tets)
    d2 = ((nodes[tets] - c[:, None]) ** 2).sum(axis=2)
    np.testing.assert_allclose(d2, np.repeat(r2[:, None], 4, axis=1), rtol=1e-9)
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    assert np.isinf(_circumspheres(flat, np.array([[0, 1, 2, 3]]))[1][0])


def test_locate_stays_in_its_tissue():
    """The visibility walk finds the tet containing a point, and stops at an interface."""
    from jaxhead.geometry.improve import _locate

    nodes, two, _ = _bipyramid(1.0)
    faces, owner, i, j, _ = face_adjacency(two)
    nbr = np.full(8, -1)
    nbr[i], nbr[j] = owner[j], owner[i]
    nbr = nbr.reshape(2, 4)
    below = nodes[:3].mean(axis=0) - [0, 0, 0.3]  # inside the second tet
    assert _locate(nodes, two, np.array([1, 1]), nbr, 0, below) == 1
    assert _locate(nodes, two, np.array([1, 2]), nbr, 0, below) == -1
    assert _locate(nodes, two, np.array([1, 1]), nbr, 0, nodes[:3].mean(axis=0) + [0, 0, 0.3]) == 0


def test_insertion_keeps_tissues_and_interfaces_on_the_needle_fan():
    """One insertion pass on the needle fan: fewer tets below the limit, every tissue volume
    (1e-9), the boundary and every interface face kept exactly, conforming and positive; the
    inserted nodes lie strictly inside one tissue and the q array matches the mesh."""
    from jaxhead.geometry.improve import LIMIT, _insert_pass, classify_nodes

    nodes, tets, labels = _needle_fan()
    q = tet_quality(nodes, tets)
    n2, t2, l2, q2, n_ins = _insert_pass(nodes, tets, labels, q, target=0.22)
    assert n_ins > 0 and len(n2) == len(nodes) + n_ins
    assert (q2 < LIMIT).sum() < (q < LIMIT).sum()
    np.testing.assert_allclose(q2, tet_quality(n2, t2))
    assert np.all(signed_volumes(n2, t2) > 0) and _conforming(t2)
    v0 = np.bincount(labels, signed_volumes(nodes, tets), minlength=5)
    v2 = np.bincount(l2, signed_volumes(n2, t2), minlength=5)
    np.testing.assert_allclose(v2, v0, rtol=1e-9, atol=1e-9)
    assert _faces(t2, l2) == _faces(tets, labels)
    assert np.all(classify_nodes(t2, l2, len(n2))[len(nodes):] == -1)


def test_improve_mends_the_needle_fan():
    """Relocation, flips and splits alone left 57 of the 75 tets below the Table-2 limit here
    (before circumcentre insertion); the improvement now leaves none, with every interface face
    and boundary face kept by node (nodes on them only slide along them)."""
    from jaxhead.geometry.improve import LIMIT, improve_mesh

    nodes, tets, labels = _needle_fan()
    assert (tet_quality(nodes, tets) < LIMIT).sum() == 75
    n2, t2, l2, stats = improve_mesh(nodes, tets, labels, _interface_projectors(nodes, tets, labels),
                                     iterations=30)
    q2 = tet_quality(n2, t2)
    assert stats["below_0.2_after"] == (q2 < LIMIT).sum() == 0, stats
    assert stats["nodes_inserted"] > 0
    assert np.all(signed_volumes(n2, t2) > 0) and _conforming(t2)
    assert _faces(t2, l2) == _faces(tets, labels)


def test_quality_matches_the_verdict_metrics():
    """The improvement's NumPy quality equals quality.tet_metrics' (the jit-compiled Verdict
    metrics) on random, inverted, flat and collapsed tets, and its helper ranges are aranges."""
    from jaxhead.geometry.improve import _ranges, _sj_cond
    from jaxhead.geometry.quality import tet_metrics

    rng = np.random.default_rng(3)
    p = rng.normal(size=(500, 4, 3)) * rng.uniform(0.1, 10, size=(500, 1, 1))
    p[1] = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 3, 0]]  # flat
    p[2] = 0.0  # collapsed to a point
    p[3] = p[3][[1, 0, 2, 3]]  # inverted copy of a random tet
    sj, cond = _sj_cond(p)
    ref = tet_metrics(p.reshape(-1, 3), np.arange(2000).reshape(-1, 4))
    np.testing.assert_allclose(sj, np.asarray(ref["scaled_jacobian"]), rtol=1e-12, atol=1e-14)
    fin = np.isfinite(np.asarray(ref["condition"]))
    assert (fin == np.isfinite(cond)).all() and not fin[1:3].any()
    np.testing.assert_allclose(cond[fin], np.asarray(ref["condition"])[fin], rtol=1e-12)
    assert (sj < 0).sum() > 100 and sj[1] == 0 and sj[2] == 0
    starts, ends = np.array([4, 0, 9, 9]), np.array([7, 2, 9, 12])
    np.testing.assert_array_equal(_ranges(starts, ends), [4, 5, 6, 0, 1, 9, 10, 11])
    assert len(_ranges(np.array([3]), np.array([3]))) == 0


#: The star (10 CSF tets) of a free node of the 2 mm skull_hole case's mesh after the improvement
#: step (gmsh, one thread, refined under 21 electrodes), node at the origin (mm): two of its tets
#: at q = 0.187 stayed below the Table-2 limit through ten restarts.
STUCK_STAR_NODES = np.array([
    [-2.528161, -0.918944, -2.745737], [0.655422, -3.087413, -0.930794],
    [1.109074, 0.528063, 2.647895], [-1.432920, 1.670849, 1.780336],
    [-0.162009, 3.031601, 0.838580], [1.373766, 2.689029, 1.130356],
    [2.132065, 2.313130, -2.348504], [0.0, 0.0, 0.0]])
STUCK_STAR_TETS = np.array([
    [2, 1, 3, 7], [0, 1, 7, 3], [2, 7, 5, 1], [0, 7, 1, 6], [7, 5, 1, 6],
    [2, 7, 3, 4], [0, 7, 4, 3], [2, 4, 5, 7], [0, 4, 7, 6], [4, 5, 7, 6]])


def test_random_candidates_reach_a_position_the_targets_miss():
    """The relocation's three targets (mean ideal apex, worst tet's ideal apex, neighbour mean, at
    four steps each) do not move this node; 64 random positions in a ball of half the star's mean
    edge do, for each of three seeds: the star's worst tet rises above the limit, none is left
    below it, and q matches the moved mesh (the acceptance rule of every relocation)."""
    from jaxhead.geometry.improve import LIMIT, _incidence, _relocate, classify_nodes

    tets = STUCK_STAR_TETS
    labels = np.full(len(tets), int(Tissue.CSF))
    cls = classify_nodes(tets, labels, len(STUCK_STAR_NODES))
    assert cls[7] == -1 and np.all(cls[:7] == 3)  # the centre is free, the star's rim held
    ptr, inc_t, inc_c = _incidence(tets, len(STUCK_STAR_NODES))
    nodes = STUCK_STAR_NODES.copy()
    q = tet_quality(nodes, tets)
    assert 0.18 < q.min() < LIMIT and (q < LIMIT).sum() == 2
    assert _relocate(nodes, tets, q, np.array([7]), cls, ptr, inc_t, inc_c, [None] * 4,
                     np.random.default_rng(0), 0) == 0
    for seed in range(3):
        nodes = STUCK_STAR_NODES.copy()
        q = tet_quality(nodes, tets)
        moved = _relocate(nodes, tets, q, np.array([7]), cls, ptr, inc_t, inc_c, [None] * 4,
                          np.random.default_rng(seed), 64)
        assert moved == 1 and q.min() > LIMIT, (seed, q.min())
        np.testing.assert_allclose(q, tet_quality(nodes, tets))
        np.testing.assert_array_equal(nodes[:7], STUCK_STAR_NODES[:7])


# ---------------------------------------------------------------------------------------------
# Edge splits on any edge, and the repair of tets with no free node (repair_stuck)


def _box(n=3, interface_x=2):
    """n^3 unit cubes, six Freudenthal tets each, positively oriented; label 1 for x < interface_x
    and 2 beyond, so the plane x = interface_x is an interface and the box's faces the boundary."""
    from itertools import permutations

    from jaxhead.geometry import orient_tets

    g = np.stack(np.meshgrid(*[np.arange(n + 1.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = lambda p: int(p[0] * (n + 1) ** 2 + p[1] * (n + 1) + p[2])  # noqa: E731
    tets, labels = [], []
    for c in np.ndindex(n, n, n):
        for perm in permutations(range(3)):
            p = np.array(c)
            t = [idx(p)]
            for axis in perm:
                p = p.copy()
                p[axis] += 1
                t.append(idx(p))
            tets.append(t)
            labels.append(1 if c[0] < interface_x else 2)
    tets, _ = orient_tets(g, np.array(tets))
    return g, tets, np.array(labels)


def _interface_triangles(nodes, tets, labels):
    """{(label pair or 'boundary'): (triangles as node triples, total area)}."""
    faces, owner, i, j, boundary = face_adjacency(tets)
    out = {}
    groups = {"boundary": faces[boundary]}
    la, lb = labels[owner[i]], labels[owner[j]]
    for a, b in {(min(x, y), max(x, y)) for x, y in zip(la, lb) if x != y}:
        groups[(a, b)] = faces[i[(np.minimum(la, lb) == a) & (np.maximum(la, lb) == b) & (la != lb)]]
    for k, f in groups.items():
        p = nodes[f]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
        out[k] = ({tuple(sorted(x)) for x in f.tolist()}, area)
    return out


def test_split_edges_keeps_volumes_orientation_and_surfaces():
    """An edge inside one tissue, one on the interface and one on the boundary, split at their
    midpoints in one call: each ring's tets become two, every tissue's volume is kept (1e-12),
    every tet stays positive, the mesh conforming; the interface and boundary triangles are the
    same surfaces (same area; a triangle through a split edge is replaced by its two halves)."""
    from jaxhead.geometry.improve import split_edges

    nodes, tets, labels = _box()
    x = nodes
    on_iface = lambda i: x[i, 0] == 2  # noqa: E731
    on_bound = lambda i: np.any((x[i] == 0) | (x[i] == 3))  # noqa: E731
    pairs = {tuple(sorted(e)) for t in tets.tolist() for e in
             [(t[a], t[b]) for a in range(4) for b in range(a + 1, 4)]}
    inside = next(e for e in sorted(pairs) if x[e[0], 0] < 2 and x[e[1], 0] < 2
                  and not on_bound(e[0]) and not on_bound(e[1]))
    iface = next(e for e in sorted(pairs) if on_iface(e[0]) and on_iface(e[1])
                 and not on_bound(e[0]) and not on_bound(e[1]))
    bound = next(e for e in sorted(pairs) if x[e[0], 2] == 0 and x[e[1], 2] == 0 and x[e[0], 0] > 2.5)
    edges = np.array([inside, iface, bound])
    ptr_star = [np.nonzero(np.isin(tets, e).sum(axis=1) == 2)[0] for e in edges]
    assert len({int(t) for s in ptr_star for t in s}) == sum(len(s) for s in ptr_star)  # no shared tet
    before = _interface_triangles(nodes, tets, labels)
    n2, t2, l2 = split_edges(nodes, tets, labels, edges)
    assert len(n2) == len(nodes) + 3 and len(t2) == len(tets) + sum(len(s) for s in ptr_star)
    np.testing.assert_array_equal(n2[-3:], 0.5 * (nodes[edges[:, 0]] + nodes[edges[:, 1]]))
    assert np.all(signed_volumes(n2, t2) > 0) and _conforming(t2)
    for lab in (1, 2):
        assert signed_volumes(n2, t2[l2 == lab]).sum() == pytest.approx(
            signed_volumes(nodes, tets[labels == lab]).sum(), rel=1e-12)
    after = _interface_triangles(n2, t2, l2)
    assert after.keys() == before.keys()
    for k, (tris, area) in before.items():
        new_tris, new_area = after[k]
        assert new_area == pytest.approx(area, rel=1e-12), k
        # Undo the splits: a half (m, j, x) is (i, j, x) with m -> i, the other with m -> j.
        parents = set()
        for tri in new_tris:
            mids = [v for v in tri if v >= len(nodes)]
            if not mids:
                parents.add(tri)
                continue
            i, j = edges[mids[0] - len(nodes)]
            other = [v for v in tri if v != mids[0]]
            assert i in other or j in other
            parents.add(tuple(sorted(other + [j if i in other else i])))
        assert parents == tris, k
    # The inside edge's new node is free; the interface one is on the interface; the boundary one on it.
    from jaxhead.geometry.improve import classify_nodes

    c = classify_nodes(t2, l2, len(n2))[-3:]
    assert c[0] == -1 and c[1] == 0 and c[2] == 3


def test_split_edges_rejects_bad_edges():
    from jaxhead.geometry.improve import split_edges

    nodes, tets, labels = _box(n=1)
    with pytest.raises(ValueError, match="not an edge of the mesh"):
        split_edges(nodes, tets, labels, np.array([[0, 0]]))
    with pytest.raises(ValueError, match="shares a tet"):
        split_edges(nodes, tets, labels, tets[0, [[0, 1], [2, 3]]])
    with pytest.raises(ValueError, match=r"`edges` must be \(k, 2\)"):
        split_edges(nodes, tets, labels, np.array([0, 1]))


#: The piece of the MNI152-based head's mesh (true labels, 1 mm, 10-20 electrodes, gmsh and the
#: improvement with its three restarts; 218,896 tets) within three node rings of the three tets
#: it left below the Table-2 limit (2118 tets, BRAIN and CSF), with the input brain surface
#: (refined under the electrodes, as meshed) around it. The three are CSF tets at the frontal
#: midline (q 0.126-0.128, scaled Jacobian ~0.13) in a one-tet-thick channel of CSF between two
#: folds of the brain surface (the interhemispheric fissure), each with two faces on the brain
#: surface; all four nodes and all six edges of each lie on it. Nodes in mm, shifted by `offset`.
STUCK_CHANNEL = __import__("pathlib").Path(__file__).resolve().parent / "data" / "stuck_csf_channel_mni152.npz"


def _stuck_channel():
    """(nodes, tets, labels, projectors (the brain surface's closest point; no other surface
    meets the piece), fixed (the piece's border, held as the rest of the head holds it))."""
    import gpytoolbox

    z = np.load(STUCK_CHANNEL)
    nodes, tets, labels = z["nodes"].astype(float), z["tets"].astype(np.int64), z["labels"].astype(np.int64)
    bv, bf = z["brain_vertices"].astype(float), z["brain_faces"].astype(np.int32)

    def brain(q):
        if len(q) == 0:
            return np.asarray(q)
        _, idx, lam = gpytoolbox.squared_distance(np.ascontiguousarray(q, dtype=float), bv, bf, use_cpp=True)
        return np.einsum("ij,ijk->ik", lam, bv[bf[idx]])

    faces, _, _, _, boundary = face_adjacency(tets)
    fixed = np.zeros(len(nodes), dtype=bool)
    fixed[faces[boundary]] = True
    return nodes, tets, labels, [brain, None, None, None], fixed, (bv, bf)


def test_repair_mends_a_csf_channel_with_no_free_node():
    """The improvement (relocation with random candidates, flips, insertion, interior edge
    splits; the mesh stage's three restarts) cannot raise these tets: every node is on the brain
    surface and so is every edge, so there is no free node to move and no interior edge to
    split. repair_stuck (longest-edge bisection including surface edges, then the improvement
    on the piece around them) takes the minimum quality above 0.2. The piece's total volume is
    kept (its border is fixed), BRAIN and CSF exchange only what sliding nodes along the brain
    surface exchanges (< 1 %), every node on the brain interface lies on the input surface."""
    import gpytoolbox

    from jaxhead.geometry.improve import LIMIT, _incidence, classify_nodes, improve_mesh, repair_stuck

    nodes, tets, labels, project, fixed, (bv, bf) = _stuck_channel()
    q = tet_quality(nodes, tets)
    bad = np.nonzero(q < LIMIT)[0]
    assert len(bad) == 3 and np.all(labels[bad] == int(Tissue.CSF)) and q.min() < 0.13
    cls = classify_nodes(tets, labels, len(nodes))
    assert np.all(cls[tets[bad]] == 0)  # every node on the brain surface
    ptr, inc_t, _ = _incidence(tets, len(nodes))
    for t in bad:  # every edge of each has a brain tet around it: no edge inside the CSF
        for a in range(4):
            for b in range(a + 1, 4):
                i, j = tets[t, a], tets[t, b]
                ring = np.intersect1d(inc_t[ptr[i]:ptr[i + 1]], inc_t[ptr[j]:ptr[j + 1]])
                assert np.any(labels[ring] == int(Tissue.BRAIN))
    for seed in (1, 2, 3):  # the mesh stage's restarts leave them
        stats = improve_mesh(nodes, tets, labels, project, iterations=30, seed=seed, flip_cycles=12,
                             random_candidates=64, fixed=fixed)[3]
        assert stats["below_0.2_after"] == 3, stats

    n2, t2, l2, rep = repair_stuck(nodes, tets, labels, project, fixed=fixed)
    q2 = tet_quality(n2, t2)
    assert rep["below_0.2_after"] == (q2 < LIMIT).sum() == 0 and q2.min() > LIMIT, rep
    assert rep["surface_edges_bisected"] > 0 and rep["nodes_added"] == len(n2) - len(nodes) > 0
    assert np.all(signed_volumes(n2, t2) > 0) and _conforming(t2)
    np.testing.assert_array_equal(n2[:len(nodes)][fixed], nodes[fixed])
    assert signed_volumes(n2, t2).sum() == pytest.approx(signed_volumes(nodes, tets).sum(), rel=1e-12)
    for lab in (1, 2):
        assert signed_volumes(n2, t2[l2 == lab]).sum() == pytest.approx(
            signed_volumes(nodes, tets[labels == lab]).sum(), rel=1e-2)
    on = np.nonzero(classify_nodes(t2, l2, len(n2)) == 0)[0]
    d2, _, _ = gpytoolbox.squared_distance(n2[on], bv, bf, use_cpp=True)
    assert np.sqrt(d2).max() < 1e-9


def test_repair_does_nothing_on_a_clean_mesh():
    from jaxhead.geometry.improve import repair_stuck

    nodes, tets, labels = _box()
    out = repair_stuck(nodes, tets, labels, [None] * 4)
    assert out[0] is nodes or np.array_equal(out[0], nodes)
    assert np.array_equal(out[1], tets) and np.array_equal(out[2], labels)
    assert out[3]["rounds"] == 0 and out[3]["nodes_added"] == 0
