"""Reading and writing tetrahedral meshes and triangle surfaces.  [host]

Tetrahedral meshes go through meshio (Gmsh ``.msh``, VTK ``.vtu``) and scipy.io (MATLAB ``.mat``),
surfaces through trimesh (``.stl``, ``.ply``, ``.obj``). Every file is written atomically
(:func:`jaxhead.io.atomic_write_path`).
"""

from __future__ import annotations

import contextlib
import io as stdio
import logging
import os
import struct
import zlib
from pathlib import Path

import meshio
import numpy as np
import scipy.io
import trimesh
from nibabel.filebasedimages import ImageFileError
from nibabel.spatialimages import HeaderDataError

from .._files import atomic_write_path
from ..geometry.surface import Surface
from ..geometry.tetmesh import TetMesh, orient_tets
from ..tissue import TISSUES, Tissue

log = logging.getLogger(__name__)

#: Tetrahedral mesh formats of save_mesh/load_mesh.
MESH_EXTENSIONS: tuple[str, ...] = (".msh", ".vtu", ".mat")
#: Triangle surface formats of save_surface/load_surface.
SURFACE_EXTENSIONS: tuple[str, ...] = (".stl", ".ply", ".obj")

# Errors nibabel, gzip and numpy raise on damaged or foreign files.
_READ_ERRORS = (
    ImageFileError, HeaderDataError, OSError, EOFError, ValueError, zlib.error, struct.error,
    TypeError, KeyError, IndexError,
)


# Tetrahedral meshes
# ---------------------------------------------------------------------------------------------


def _ext(path: Path, supported: tuple[str, ...], what: str) -> str:
    ext = path.suffix.lower()
    if ext not in supported:
        raise ValueError(
            f"{str(path)!r}: unsupported {what} extension {ext or '(none)'!r}; "
            f"supported: {', '.join(supported)}."
        )
    return ext


def save_mesh(mesh: TetMesh, path: str | os.PathLike, *, binary: bool = True) -> Path:
    """Write a TetMesh; the extension picks the format. Atomic.

    Formats:
        ``.msh``: Gmsh 2.2 (readable by Gmsh, SimNIBS, EIDORS' gmsh_mk_fwd_model), via meshio.
            Each tissue is a physical volume: cell data ``gmsh:physical`` = ``gmsh:geometrical``
            = the Tissue value (1..4), named BRAIN, CSF, SKULL, SCALP in $PhysicalNames.
        ``.vtu``: VTK unstructured grid for ParaView, via meshio; tissue in cell data "tissue".
        ``.mat``: MATLAB v5 via scipy.io.savemat, the seed paper's final format:
            ``node`` (n_nodes, 3) double, mm; ``element`` (n_tets, 4) double, 1-based node
            indices (MATLAB/EIDORS indexing; double, as MATLAB's sparse() needs);
            ``tissue`` (n_tets, 1) double, Tissue values 1..4; ``tissue_names`` 1x4 cell
            {'brain','csf','skull','scalp'} indexed by tissue value. In EIDORS:
            ``fmdl.nodes = node; fmdl.elems = element;`` (then mm -> m if wanted).

    Arguments:
        mesh: the mesh (positively oriented tets, node coordinates in mm).
        path: target file.
        binary: binary .msh / compressed binary .vtu (default); False for ASCII.

    Returns:
        the path written.
    """
    if not isinstance(mesh, TetMesh):
        raise TypeError(f"save_mesh needs a TetMesh, got {type(mesh).__name__}.")
    path = Path(path)
    ext = _ext(path, MESH_EXTENSIONS, "mesh")
    labels = mesh.labels.astype(np.int32)
    with atomic_write_path(path) as tmp:
        if ext == ".msh":
            m = meshio.Mesh(
                mesh.nodes, [("tetra", mesh.tets)],
                cell_data={"gmsh:physical": [labels], "gmsh:geometrical": [labels]},
                field_data={t.name: np.array([int(t), 3]) for t in TISSUES},
            )
            meshio.write(tmp, m, file_format="gmsh22", binary=binary)
        elif ext == ".vtu":
            m = meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)], cell_data={"tissue": [labels]})
            meshio.write(tmp, m, file_format="vtu", binary=binary)
        else:
            names = np.empty((1, len(TISSUES)), dtype=object)
            names[0, :] = [t.name.lower() for t in TISSUES]
            scipy.io.savemat(
                tmp,
                {
                    "node": mesh.nodes.astype(np.float64),
                    "element": (mesh.tets + 1).astype(np.float64),
                    "tissue": mesh.labels.astype(np.float64).reshape(-1, 1),
                    "tissue_names": names,
                },
                appendmat=False, do_compression=True, oned_as="column",
            )
    return path


def _tissue_tags(field_data: dict) -> dict[int, int]:
    """Map Gmsh physical tags to Tissue values through 3D physical names that are tissues."""
    mapping = {}
    for name, value in field_data.items():
        value = np.asarray(value).ravel()
        if value.size >= 2 and int(value[1]) != 3:
            continue
        try:
            tissue = Tissue.parse(str(name))
        except ValueError:
            continue
        if tissue != Tissue.BACKGROUND:
            mapping[int(value[0])] = int(tissue)
    return mapping


def _mesh_from_meshio(path: Path, ext: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    said = stdio.StringIO()
    try:
        # meshio prints its reasons and calls sys.exit(1) when no reader accepts the file.
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(path, file_format="gmsh" if ext == ".msh" else "vtu")
    except (Exception, SystemExit) as e:  # ReadError, ValueError, KeyError, ... and exit
        why = " ".join(said.getvalue().split()) or f"{type(e).__name__}: {e}"
        raise ValueError(
            f"{str(path)!r} could not be read as a {ext} mesh ({why}); check that the file is "
            "complete and in the format its extension says."
        ) from e
    blocks = [i for i, c in enumerate(m.cells) if c.type == "tetra"]
    if not blocks:
        raise ValueError(
            f"{str(path)!r} has no linear tetrahedra (cell types: "
            f"{sorted({c.type for c in m.cells}) or 'none'}); jaxhead needs a 'tetra' mesh."
        )
    tets = np.concatenate([m.cells[i].data for i in blocks])
    key = "gmsh:physical" if ext == ".msh" else "tissue"
    if key not in m.cell_data:
        raise ValueError(
            f"{str(path)!r} has no cell data {key!r} giving each tet's tissue (it has "
            f"{sorted(m.cell_data) or 'none'}); label the tets with Tissue values 1..4."
        )
    labels = np.concatenate([np.asarray(m.cell_data[key][i]).ravel() for i in blocks])
    labels = labels.astype(np.int64)
    if ext == ".msh":
        tag_map = _tissue_tags(m.field_data)
        if tag_map:
            unknown = sorted(set(np.unique(labels).tolist()) - set(tag_map))
            if unknown:
                raise ValueError(
                    f"{str(path)!r}: physical tags {unknown} have no tissue name; name every "
                    "volume group BRAIN, CSF, SKULL or SCALP."
                )
            labels = np.vectorize(tag_map.get, otypes=[np.int64])(labels)
    return np.asarray(m.points, dtype=np.float64), tets, labels


def _mesh_from_mat(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        d = scipy.io.loadmat(path, appendmat=False)
    except Exception as e:  # scipy raises ValueError, TypeError, MatReadError on bad files
        raise ValueError(
            f"{str(path)!r} could not be read as a MATLAB .mat file ({type(e).__name__}: {e})."
        ) from e

    def get(*names):
        for n in names:
            if n in d:
                return np.asarray(d[n])
        found = sorted(k for k in d if not k.startswith("__"))
        raise ValueError(
            f"{str(path)!r} has no variable {' or '.join(map(repr, names))} (it has {found}); "
            "a jaxhead .mat mesh holds node (n,3), element (m,4) 1-based and tissue (m,1)."
        )

    nodes = get("node", "nodes")
    elements = get("element", "elements", "elems")
    labels = get("tissue").ravel()
    if elements.ndim != 2 or elements.shape[1] != 4:
        raise ValueError(f"{str(path)!r}: `element` must be (n_tets, 4), got {elements.shape}.")
    if elements.size and (not np.all(elements == np.round(elements)) or elements.min() < 1):
        raise ValueError(
            f"{str(path)!r}: `element` must hold 1-based integer node indices (MATLAB "
            f"convention); its minimum is {elements.min()}. Add 1 to 0-based indices."
        )
    if not np.all(labels == np.round(labels)):
        raise ValueError(f"{str(path)!r}: `tissue` must hold integer Tissue values 1..4.")
    return nodes.astype(np.float64), elements.astype(np.int64) - 1, labels.astype(np.int64)


def load_mesh(path: str | os.PathLike, *, reorient: bool = False) -> TetMesh:
    """Read a TetMesh written by :func:`save_mesh` (or another tool, in the same layout).

    For ``.msh``, tissues come from the physical tags (``gmsh:physical``); if the file names its
    3D physical groups after tissues (BRAIN, CSF, SKULL, SCALP, any case), tags are mapped
    through those names, so files numbering their groups differently load correctly.
    Gmsh 2.2, 4.0 and 4.1 files are read (meshio).

    Arguments:
        path: ``.msh``, ``.vtu`` or ``.mat``.
        reorient: fix negatively oriented tets by swapping two nodes (the count is logged);
            by default such a file is rejected.

    Returns:
        TetMesh with nodes (n_nodes, 3) mm, tets (n_tets, 4) 0-based, labels (n_tets,).
    """
    path = Path(path)
    ext = _ext(path, MESH_EXTENSIONS, "mesh")
    if not path.is_file():
        raise FileNotFoundError(f"{str(path)!r}: no such file; check the path.")
    nodes, tets, labels = _mesh_from_mat(path) if ext == ".mat" else _mesh_from_meshio(path, ext)
    if reorient and nodes.ndim == 2 and nodes.shape[1] == 3 and tets.size:
        tets, n_flipped = orient_tets(nodes, tets)
        if n_flipped:
            log.info("%s: reoriented %d of %d tets", path, n_flipped, len(tets))
    try:
        return TetMesh(nodes, tets, labels)
    except ValueError as e:
        hint = "" if reorient else " (pass reorient=True to fix the tets' orientation)"
        raise ValueError(f"{str(path)!r}: {e}{hint if 'oriented' in str(e) else ''}") from e


# ---------------------------------------------------------------------------------------------
# Surfaces
# ---------------------------------------------------------------------------------------------


def save_surface(surface: Surface, path: str | os.PathLike) -> Path:
    """Write a Surface via trimesh; the extension picks the format. Atomic.

    ``.stl`` is binary STL (float32 coordinates, vertices not shared); ``.ply`` is binary PLY
    (float32 coordinates); ``.obj`` is text with 8 decimals. Face winding (outward normals) is
    kept by all three.

    Arguments:
        surface: the surface (vertices in mm).
        path: target file.

    Returns:
        the path written.
    """
    if not isinstance(surface, Surface):
        raise TypeError(f"save_surface needs a Surface, got {type(surface).__name__}.")
    path = Path(path)
    ext = _ext(path, SURFACE_EXTENSIONS, "surface")
    tm = trimesh.Trimesh(surface.vertices, surface.faces, process=False)
    with atomic_write_path(path) as tmp:
        tm.export(file_obj=str(tmp), file_type=ext[1:])
    return path


def load_surface(path: str | os.PathLike, tissue: Tissue | str | int) -> Surface:
    """Read a triangle surface via trimesh, as the outer surface of `tissue`'s nested solid.

    STL stores no shared vertices: coincident vertices are merged (trimesh.merge_vertices)
    so that the result is an indexed, connected surface. Vertex order and faces are otherwise
    kept as stored.

    Arguments:
        path: ``.stl``, ``.ply`` or ``.obj``.
        tissue: the Tissue the surface bounds (name, value or Tissue).

    Returns:
        Surface with vertices (n_verts, 3) mm and faces (n_faces, 3).
    """
    path = Path(path)
    ext = _ext(path, SURFACE_EXTENSIONS, "surface")
    tissue = Tissue.parse(tissue)
    if not path.is_file():
        raise FileNotFoundError(f"{str(path)!r}: no such file; check the path.")
    try:
        tm = trimesh.load(str(path), file_type=ext[1:], force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on malformed files
        raise ValueError(
            f"{str(path)!r} could not be read as {ext} ({type(e).__name__}: {e})."
        ) from e
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise ValueError(f"{str(path)!r} holds no triangles; pass a triangle surface file.")
    if ext == ".stl":
        tm.merge_vertices()
    try:
        return Surface(np.asarray(tm.vertices), np.asarray(tm.faces), tissue)
    except ValueError as e:
        raise ValueError(f"{str(path)!r}: {e}") from e

