"""Core types validate themselves: Tissue, Volume, LabelMap, TetMesh, Surface."""

import equinox as eqx
import jax
import numpy as np
import pytest

from jaxhead import LabelMap, Surface, TetMesh, Tissue, Volume, default_sigma, orient_tets
from jaxhead.geometry import signed_volumes
from jaxhead.volume import default_affine, voxel_sizes


def test_tissue_order_and_parse():
    assert [int(t) for t in Tissue] == [0, 1, 2, 3, 4]
    assert Tissue.parse("Skull") is Tissue.SKULL
    assert Tissue.parse(4) is Tissue.SCALP
    with pytest.raises(ValueError, match="unknown tissue 'bone'"):
        Tissue.parse("bone")
    with pytest.raises(ValueError, match="not a Tissue"):
        Tissue.parse(9)
    s = default_sigma()
    assert s.dtype == np.float64 and s.shape == (4,)
    # CSF conducts best, skull worst (Baumann 1997; Horesh 2006).
    assert s.argmax() == 1 and s.argmin() == 2


def test_volume_validation():
    v = Volume(np.ones((4, 5, 6)), default_affine(2.0, (4, 5, 6)))
    np.testing.assert_allclose(v.voxel_mm, [2, 2, 2])
    # The grid centre sits at world (0, 0, 0).
    np.testing.assert_allclose(v.affine @ [1.5, 2, 2.5, 1], [0, 0, 0, 1])
    with pytest.raises(ValueError, match="3D"):
        Volume(np.ones((4, 5)), np.eye(4))
    with pytest.raises(ValueError, match="NaN/Inf"):
        Volume(np.full((3, 3, 3), np.nan), np.eye(4))
    with pytest.raises(ValueError, match="singular"):
        Volume(np.ones((3, 3, 3)), np.diag([1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="4x4"):
        Volume(np.ones((3, 3, 3)), np.eye(3))


def test_labelmap_validation_and_volumes():
    lab = np.zeros((4, 4, 4), np.int32)
    lab[1:3, 1:3, 1:3] = 1
    m = LabelMap(lab, np.diag([2.0, 1.0, 1.0, 1.0]))
    assert m.tissue_volumes_mm3()[Tissue.BRAIN] == 8 * 2.0
    assert m.mask("brain").sum() == 8
    with pytest.raises(ValueError, match="outside 0..4"):
        LabelMap(lab + 5, np.eye(4))
    with pytest.raises(ValueError, match="non-integer"):
        LabelMap(lab + 0.5, np.eye(4))


def test_voxel_sizes_of_rotated_affine():
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    aff = np.eye(4)
    aff[:3, :3] = rot @ np.diag([1.0, 2.0, 3.0])
    np.testing.assert_allclose(voxel_sizes(aff), [1, 2, 3])


def _two_tets():
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    return nodes, tets


def test_tetmesh_helpers():
    nodes, tets = _two_tets()
    mesh = TetMesh(nodes, tets, [1, 2])
    # Volumes: the corner tet 1/6; the other 1/3 (computed by hand from the triple product).
    np.testing.assert_allclose(mesh.tet_volumes(), [1 / 6, 1 / 3])
    faces, owner = mesh.boundary_faces()
    assert len(faces) == 6 and set(owner) == {0, 1}
    # Outward orientation: each boundary face's normal points away from its tet's centroid.
    p = nodes[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", n, p.mean(1) - mesh.centroids()[owner]) > 0)
    # The shared face is the BRAIN/CSF interface, oriented from brain to csf.
    f = mesh.interface_faces("brain", "csf")
    assert f.shape == (1, 3)
    q = nodes[f[0]]
    assert np.dot(np.cross(q[1] - q[0], q[2] - q[0]), q.mean(0) - mesh.centroids()[0]) > 0


def test_tetmesh_rejects_bad_input():
    nodes, tets = _two_tets()
    with pytest.raises(ValueError, match="one Tissue label per tet"):
        TetMesh(nodes, tets, [1])
    with pytest.raises(ValueError, match="tissues 1..4"):
        TetMesh(nodes, tets, [0, 1])
    with pytest.raises(ValueError, match="indexes nodes"):
        TetMesh(nodes, tets + 1, [1, 1])
    flipped = tets[:, [0, 1, 3, 2]]
    with pytest.raises(ValueError, match="negatively oriented"):
        TetMesh(nodes, flipped, [1, 1])
    fixed, n = orient_tets(nodes, flipped)
    assert n == 2 and np.all(signed_volumes(nodes, fixed) > 0)


def test_modules_are_pytrees():
    nodes, tets = _two_tets()
    mesh = TetMesh(nodes, tets, [1, 2])
    leaves = jax.tree_util.tree_leaves(mesh)
    assert len(leaves) == 3
    moved = eqx.tree_at(lambda m: m.nodes, mesh, nodes + 1.0)
    np.testing.assert_allclose(moved.nodes, nodes + 1)
    s = Surface(nodes[:4], tets[:1, :3], "brain")
    assert s.tissue is Tissue.BRAIN
