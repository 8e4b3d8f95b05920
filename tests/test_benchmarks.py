"""The benchmark scripts' command lines: their defaults are the library's."""

from jaxhead.geometry import MeshConfig


def test_mesh_benchmark_threads_default_is_the_library_default():
    """benchmarks/mesh.py times the mesh the library makes: gmsh with MeshConfig().threads (1,
    repeatable), not all cores (it defaulted to 0 while the library default was 1)."""
    from benchmarks.mesh import build_parser

    assert build_parser().parse_args([]).threads == MeshConfig().threads
    assert build_parser().parse_args(["--threads", "0"]).threads == 0

