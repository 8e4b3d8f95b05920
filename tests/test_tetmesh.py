"""The one tet-volume formula, enclosed volumes and face adjacency, against independent references."""

import itertools

import jax  # float64: tests/conftest.py
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

from jaxhead.geometry import TetMesh, enclosed_volume, face_adjacency, orient_tets, signed_volumes
from jaxhead.tissue import Tissue



def _random_tets(n=50, seed=0):
    rng = np.random.default_rng(seed)
    nodes = rng.normal(size=(4 * n, 3)) * [3.0, 1.0, 2.0] + [10.0, -5.0, 40.0]
    return nodes, np.arange(4 * n).reshape(n, 4)


def _delaunay(n=60, seed=1):
    pts = np.random.default_rng(seed).uniform(-10, 10, size=(n, 3))
    tets, _ = orient_tets(pts, Delaunay(pts).simplices)
    return pts, tets


def test_signed_volumes_equal_the_4x4_determinant_and_the_hull():
    nodes, tets = _random_tets()
    v = signed_volumes(nodes, tets)
    # independent: det [[1, P0], [1, P1], [1, P2], [1, P3]] / 6
    M = np.concatenate([np.ones((len(tets), 4, 1)), nodes[tets]], axis=2)
    np.testing.assert_allclose(v, np.linalg.det(M) / 6.0, rtol=1e-12, atol=1e-12)
    # independent: the convex hull of the four points (Qhull)
    hull = np.array([ConvexHull(nodes[t]).volume for t in tets])
    np.testing.assert_allclose(np.abs(v), hull, rtol=1e-10)
    # the unit corner tet
    unit = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    assert signed_volumes(unit, np.array([[0, 1, 2, 3]]))[0] == pytest.approx(1 / 6)


def test_signed_volumes_orientation():
    nodes, tets = _random_tets(seed=2)
    v = signed_volumes(nodes, tets)
    for perm in itertools.permutations(range(4)):
        odd = sum(perm[i] > perm[j] for i in range(4) for j in range(i + 1, 4)) % 2
        np.testing.assert_allclose(signed_volumes(nodes, tets[:, perm]), -v if odd else v, rtol=1e-12)
    fixed, n_flipped = orient_tets(nodes, tets)
    assert n_flipped == int((v < 0).sum()) > 0
    assert np.all(signed_volumes(nodes, fixed) > 0)
    # a flat tet has zero volume
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    assert signed_volumes(flat, np.array([[0, 1, 2, 3]]))[0] == 0


def test_signed_volumes_jax_in_jax_out_and_its_gradient():
    nodes, tets = _random_tets(n=5, seed=3)
    v = signed_volumes(nodes, tets)
    assert isinstance(v, np.ndarray)
    vj = jax.jit(signed_volumes)(jnp.asarray(nodes), jnp.asarray(tets))
    assert isinstance(vj, jax.Array)
    np.testing.assert_allclose(np.asarray(vj), v, rtol=1e-13)
    # d vol / d P3 = ((P1 - P0) x (P2 - P0)) / 6: the area vector of the opposite face / 3
    g = jax.grad(lambda x: signed_volumes(x, tets)[0])(jnp.asarray(nodes))
    p = nodes[tets[0]]
    np.testing.assert_allclose(g[tets[0, 3]], np.cross(p[1] - p[0], p[2] - p[0]) / 6.0, rtol=1e-12)


def test_enclosed_volume_of_a_delaunay_hull_and_reversed_faces():
    pts, tets = _delaunay()
    hull = ConvexHull(pts)
    F = hull.simplices.copy()
    # orient every hull face outward (Qhull's order is arbitrary)
    c = pts.mean(axis=0)
    n = np.cross(pts[F[:, 1]] - pts[F[:, 0]], pts[F[:, 2]] - pts[F[:, 0]])
    inward = np.einsum("ij,ij->i", n, pts[F[:, 0]] - c) < 0
    F[inward] = F[inward][:, [0, 2, 1]]
    vol = enclosed_volume(pts, F)
    assert vol == pytest.approx(hull.volume, rel=1e-12)
    assert vol == pytest.approx(signed_volumes(pts, tets).sum(), rel=1e-12)
    assert enclosed_volume(pts, F[:, [0, 2, 1]]) == pytest.approx(-hull.volume, rel=1e-12)
    # invariant under a translation far from the origin
    assert enclosed_volume(pts + 1e4, F) == pytest.approx(hull.volume, rel=1e-9)


def _brute_force_pairs(tets):
    seen = {}
    for t, tet in enumerate(tets):
        for k in range(4):
            seen.setdefault(frozenset(np.delete(tet, k).tolist()), []).append(t)
    return seen


def test_face_adjacency_against_a_dictionary():
    pts, tets = _delaunay(seed=4)
    faces, owner, i, j, boundary = face_adjacency(tets)
    seen = _brute_force_pairs(tets)
    assert len(faces) == 4 * len(tets) and np.array_equal(owner, np.repeat(np.arange(len(tets)), 4))
    # every face is one of its owner's faces
    for f, t in zip(faces, owner):
        assert set(f.tolist()) < set(tets[t].tolist())
    pairs = {frozenset((owner[a], owner[b])) for a, b in zip(i, j)}
    expect = {frozenset(ts) for ts in seen.values() if len(ts) == 2}
    assert pairs == expect
    assert boundary.sum() == sum(len(ts) == 1 for ts in seen.values())
    # faces of positive tets point outward: the opposite node lies behind each face
    p = pts[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    opposite = pts[np.array([(set(tets[t].tolist()) - set(f.tolist())).pop() for f, t in zip(faces, owner)])]
    assert np.all(np.einsum("ij,ij->i", n, opposite - p[:, 0]) < 0)
    # the two copies of an interior face are the same three nodes, oppositely oriented
    assert np.array_equal(np.sort(faces[i], axis=1), np.sort(faces[j], axis=1))


def test_tetmesh_boundary_and_interface_faces():
    pts, tets = _delaunay(seed=5)
    inner = np.linalg.norm(pts[tets].mean(axis=1), axis=1) < 6.0
    labels = np.where(inner, int(Tissue.BRAIN), int(Tissue.SCALP))
    mesh = TetMesh(pts, tets, labels)
    seen = _brute_force_pairs(tets)
    f, t = mesh.boundary_faces()
    assert {frozenset(x.tolist()) for x in f} == {k for k, ts in seen.items() if len(ts) == 1}
    assert enclosed_volume(pts, f) == pytest.approx(mesh.tet_volumes().sum(), rel=1e-12)
    iface = mesh.interface_faces("brain", "scalp")
    expect = {k for k, ts in seen.items() if len(ts) == 2 and len({labels[x] for x in ts}) == 2}
    assert expect and {frozenset(x.tolist()) for x in iface} == expect and len(iface) == len(expect)
    # oriented from brain to scalp: the brain tet's fourth node lies behind the face
    brain_nodes = {k: [x for x in ts if labels[x] == int(Tissue.BRAIN)][0] for k, ts in seen.items()
                   if k in expect}
    for x in iface:
        tet = tets[brain_nodes[frozenset(x.tolist())]]
        q = pts[(set(tet.tolist()) - set(x.tolist())).pop()]
        n = np.cross(pts[x[1]] - pts[x[0]], pts[x[2]] - pts[x[0]])
        assert n @ (q - pts[x[0]]) < 0
