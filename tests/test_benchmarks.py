"""The benchmark scripts' command lines: their defaults are the library's."""

from jaxhead.geometry import MeshConfig


def test_mesh_benchmark_threads_default_is_the_library_default():
    """benchmarks/mesh.py times the mesh the library makes: gmsh with MeshConfig().threads (1,
    repeatable), not all cores (it defaulted to 0 while the library default was 1)."""
    from benchmarks.mesh import build_parser

    assert build_parser().parse_args([]).threads == MeshConfig().threads
    assert build_parser().parse_args(["--threads", "0"]).threads == 0


def test_segment_benchmark_fits_a_head_to_its_grid_without_moving_it():
    """benchmarks/segment.py's `fitted`: padded with air at the sides, cropped in the middle (x, y) or below
    (z: the neck), every kept voxel at the same world position with the same fractions."""
    import numpy as np

    from benchmarks.segment import fitted
    from jaxhead.segmentation.templates import Anatomy

    rng = np.random.default_rng(0)
    f = rng.random((6, 5, 9, 12)).astype(np.float32)
    f /= f.sum(0)
    affine = np.array([[1.0, 0, 0, -2], [0, 1, 0, -4], [0, 0, 1, -6], [0, 0, 0, 1]])
    diploe = f[4] * 0.5
    out = fitted(Anatomy(f, affine, "random", diploe=diploe), (8, 7, 10))
    assert out.shape == (8, 7, 10) and out.t1 is None and out.diploe.shape == (8, 7, 10)
    np.testing.assert_allclose(out.fractions.sum(0), 1.0, rtol=1e-6)
    for i, j, k in [(0, 1, 2), (4, 8, 11), (2, 5, 2)]:  # kept voxels: x padded by 1, y cropped by 1, z by 2
        ii, jj, kk = i + 1, j - 1, k - 2
        if 0 <= jj < 7 and 0 <= kk < 10:
            np.testing.assert_array_equal(out.fractions[:, ii, jj, kk], f[:, i, j, k])
            assert out.diploe[ii, jj, kk] == diploe[i, j, k]
            np.testing.assert_allclose(out.affine @ [ii, jj, kk, 1], affine @ [i, j, k, 1])
    assert np.all(out.fractions[0, 0] == 1.0) and np.all(out.fractions[1:, 0] == 0.0)  # the padding is air
