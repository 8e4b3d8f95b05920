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
from typing import Literal

import meshio
import numpy as np
import scipy.io
import trimesh
from nibabel.filebasedimages import ImageFileError
from nibabel.spatialimages import HeaderDataError

from .._files import atomic_write_path
from ..geometry.surface import Surface
from ..geometry.tetmesh import TetMesh, face_adjacency, orient_tets
from ..tissue import TISSUES, Tissue
from .measurements import LENGTH_UNITS, mat73_arrays

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


#: Tissue names other tools use, mapped to the four tissues (lower case, spaces or underscores).
TISSUE_SYNONYMS: dict[str, str] = {
    **{n: "brain" for n in ("brain", "grey matter", "gray matter", "gm", "white matter", "wm",
                            "grey", "gray", "white", "cerebrum", "cerebellum", "brainstem")},
    **{n: "csf" for n in ("csf", "cerebrospinal fluid", "ventricles")},
    **{n: "skull" for n in ("skull", "bone", "compact bone", "spongy bone", "cortical bone",
                            "cancellous bone")},
    **{n: "scalp" for n in ("scalp", "skin")},
}

#: SimNIBS volume tags (charm / headreco: 1 white matter, 2 grey matter, 3 CSF, 4 bone, 5 scalp,
#: 6 eye balls, 7 compact bone, 8 spongy bone, 9 blood, 10 muscle) for the four tissues. Eyes,
#: blood and muscle are left out on purpose: say where they go, e.g.
#: ``load_mesh(p, tissue_map={**SIMNIBS_TISSUE_MAP, 6: "scalp", 9: "brain", 10: "scalp"})``.
SIMNIBS_TISSUE_MAP: dict[int, str] = {1: "brain", 2: "brain", 3: "csf", 4: "skull",
                                      5: "scalp", 7: "skull", 8: "skull"}
_SIMNIBS_NAMES = {1: "white matter", 2: "grey matter", 3: "CSF", 4: "bone", 5: "scalp",
                  6: "eye balls", 7: "compact bone", 8: "spongy bone", 9: "blood", 10: "muscle"}


def _by_name(name: str) -> int | None:
    key = " ".join(str(name).lower().replace("_", " ").split())
    t = TISSUE_SYNONYMS.get(key)
    return None if t is None else int(Tissue.parse(t))


def _apply_map(path, labels: np.ndarray, tissue_map, names: dict | None = None) -> np.ndarray:
    """File labels -> Tissue values through `tissue_map` ({label or name: tissue}) and, for
    labels it does not name, the file's own names (`names`: {label: name}); unmapped labels
    are an error listing them and the fix."""
    mapping: dict[int, int] = {}
    names = names or {}
    user = dict(SIMNIBS_TISSUE_MAP if isinstance(tissue_map, str) and tissue_map == "simnibs"
                else (tissue_map or {}))
    if isinstance(tissue_map, str) and tissue_map != "simnibs":
        raise ValueError(f"`tissue_map` = {tissue_map!r}; pass 'simnibs' or a dict "
                         "{file label or name: tissue}.")
    by_label_name = {str(v).lower(): k for k, v in names.items()}
    for key, tissue in user.items():
        t = int(Tissue.parse(tissue))
        if t == int(Tissue.BACKGROUND):
            raise ValueError(f"`tissue_map[{key!r}]` is background; every tet needs a tissue.")
        if isinstance(key, str):
            if key.lower() not in by_label_name:
                raise ValueError(f"{str(path)!r}: `tissue_map` names {key!r}, which the file does "
                                 f"not (its tissues: {sorted(names.values())}).")
            mapping[by_label_name[key.lower()]] = t
        else:
            mapping[int(key)] = t
    for label, name in names.items():
        if label not in mapping and _by_name(name) is not None:
            mapping[label] = _by_name(name)
    present = sorted(set(np.unique(labels).tolist()))
    unmapped = [x for x in present if x not in mapping]
    if unmapped:
        desc = ", ".join(f"{x} ({names[x]})" if x in names else str(x) for x in unmapped)
        raise ValueError(
            f"{str(path)!r}: tissue labels {desc} have no jaxhead tissue; pass tissue_map="
            "{label or name: 'brain' | 'csf' | 'skull' | 'scalp', ...} for every one"
            + (" (SimNIBS: start from jaxhead.io.SIMNIBS_TISSUE_MAP)." if names == {} else "."))
    lut = np.zeros(max(present) + 1, np.int64)
    for k, v in mapping.items():
        if k <= max(present):
            lut[k] = v
    if min(present) < 0:
        raise ValueError(f"{str(path)!r}: negative tissue labels {min(present)}.")
    return lut[labels]


def _mesh_from_meshio(path: Path, ext: str, tissue_map=None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    if ext == ".msh" and tissue_map is not None:
        names = {int(np.asarray(v).ravel()[0]): str(k) for k, v in m.field_data.items()
                 if np.asarray(v).size < 2 or int(np.asarray(v).ravel()[1]) == 3}
        return np.asarray(m.points, dtype=np.float64), tets, _apply_map(path, labels,
                                                                        tissue_map, names)
    if ext == ".msh" and not _tissue_tags(m.field_data) and (
            np.unique(labels).size > 4 or labels.max() > 4):
        found = sorted(set(np.unique(labels).tolist()))
        desc = ", ".join(f"{t} ({_SIMNIBS_NAMES.get(t, '?')})" for t in found)
        raise ValueError(
            f"{str(path)!r}: volume tags {found} carry no tissue names and are not jaxhead's "
            f"1..4; if this is a SimNIBS mesh ({desc}) pass tissue_map='simnibs' (plus where "
            "eyes, blood, muscle go), else tissue_map={tag: tissue}.")
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


def _mat_variables(path: Path) -> dict:
    """Variables of a .mat file (v5 through scipy, v7.3 through h5py), structs flattened to
    dotted names ("materials.ref"), cells of strings to lists of str."""
    try:
        d = scipy.io.loadmat(path, appendmat=False)
    except NotImplementedError:  # v7.3
        return mat73_arrays(path)
    except Exception as e:  # scipy raises ValueError, TypeError, MatReadError on bad files
        raise ValueError(
            f"{str(path)!r} could not be read as a MATLAB .mat file ({type(e).__name__}: {e})."
        ) from e
    out = {}
    for k, v in d.items():
        if k.startswith("__"):
            continue
        if isinstance(v, np.ndarray) and v.dtype.names:  # a struct
            s = scipy.io.loadmat(path, appendmat=False, simplify_cells=True,
                                 variable_names=[k])[k]
            for f, x in s.items():
                out[f"{k}.{f}"] = ([str(n) for n in x] if isinstance(x, (list, np.ndarray))
                                   and np.asarray(x, dtype=object).dtype == object
                                   and all(isinstance(n, str) for n in x) else np.asarray(x))
        else:
            out[k] = v
    return out


def _mesh_from_eidors(path: Path, d: dict, tissue_map, units):
    """EIDORS contributed head meshes: vtx (n, 3), tri/simp (m, 4) 1-based, materials.ref (m,)
    1-based into materials.names."""
    nodes = np.asarray(d["vtx"], dtype=np.float64)
    key = next((k for k in ("tri", "simp", "elems", "element") if k in d), None)
    if key is None:
        raise ValueError(f"{str(path)!r}: an EIDORS-style mesh (vtx) without elements: no tri, "
                         f"simp or elems (it has {sorted(d)}).")
    tets = np.asarray(d[key])
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"{str(path)!r}: `{key}` has shape {tets.shape}; jaxhead needs "
                         "tetrahedra (n_tets, 4).")
    if not np.all(tets == np.round(tets)) or tets.min() < 1:
        raise ValueError(f"{str(path)!r}: `{key}` must hold 1-based node indices (MATLAB); its "
                         f"minimum is {tets.min()}. Add 1 to 0-based indices.")
    ref = d.get("materials.ref", d.get("mat_ref"))
    if ref is None:
        raise ValueError(f"{str(path)!r}: no materials.ref (a tissue per element); it has "
                         f"{sorted(d)}.")
    ref = np.asarray(ref).ravel().astype(np.int64)
    if ref.size != tets.shape[0]:
        raise ValueError(f"{str(path)!r}: materials.ref has {ref.size} entries for "
                         f"{tets.shape[0]} elements.")
    raw = d.get("materials.names", [])
    names = {i + 1: str(n) for i, n in enumerate([raw] if isinstance(raw, str) else raw)}
    if units is None:
        extent = float(np.ptp(nodes, axis=0).max()) if nodes.size else 0.0
        if extent < 1.0:
            raise ValueError(f"{str(path)!r}: the mesh spans {extent:.3g} units; a head in mm "
                             "spans ~200. If vtx is in metres pass units='m'.")
        units = "mm"
    if units not in LENGTH_UNITS:
        raise ValueError(f"`units` = {units!r}; use one of {sorted(LENGTH_UNITS)}.")
    nodes = nodes * LENGTH_UNITS[units]
    return nodes, tets.astype(np.int64) - 1, _apply_map(path, ref, tissue_map, names)


def _mesh_from_mat(path: Path, tissue_map=None, units=None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = _mat_variables(path)
    if "vtx" in d:
        return _mesh_from_eidors(path, d, tissue_map, units)

    def get(*names):
        for n in names:
            if n in d:
                return np.asarray(d[n])
        found = sorted(k for k in d if not k.startswith("__"))
        raise ValueError(
            f"{str(path)!r} has no variable {' or '.join(map(repr, names))} (it has {found}); "
            "a jaxhead .mat mesh holds node (n,3), element (m,4) 1-based and tissue (m,1); an "
            "EIDORS one vtx (n,3), tri or simp (m,4) 1-based and materials.ref/names."
        )

    nodes = get("node", "nodes")
    elements = get("element", "elements", "elems")
    labels = get("tissue").ravel()
    if tissue_map is not None:
        labels = _apply_map(path, np.asarray(labels).astype(np.int64), tissue_map)
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


def head_facing(nodes: np.ndarray, tets: np.ndarray) -> dict:
    """Which horizontal axis a head mesh faces, from where its neck is.  [host]

    The lowest 15 % (in z) of the outer boundary is the neck (or the cut through it), which
    lies behind the cranium: the vector from the centroid of the neck's boundary nodes to that
    of the upper half's points backwards (the phantom head: 18 mm). Below 3 % of the head's
    height the direction is undetermined and nothing is claimed: a sphere, a head cut above the
    neck, and a neck straight under the cranium, as in the MNI152-based head cut at the neck
    (`experiments/mni152_chain.py`: 1.4 mm against a 7.7 mm threshold). Superior is assumed to
    be +z.

    Returns:
        dict: "anterior" ("+y", "-y", "+x", "-x" or None when undetermined), "angle_deg"
        (anterior direction's angle from +y, counter-clockwise seen from above),
        "neck_offset_mm" (neck centroid minus upper-head centroid, (2,) xy mm).
    """
    faces, _, _, _, boundary = face_adjacency(tets)
    p = nodes[np.unique(faces[boundary])]
    z0, z1 = p[:, 2].min(), p[:, 2].max()
    h = z1 - z0
    d = p[p[:, 2] <= z0 + 0.15 * h, :2].mean(0) - p[p[:, 2] >= z1 - 0.5 * h, :2].mean(0)
    out = {"anterior": None, "angle_deg": float("nan"), "neck_offset_mm": d}
    if np.linalg.norm(d) < 0.03 * h:
        return out
    ang = float(np.degrees(np.arctan2(d[0], -d[1])))  # direction -d measured from +y (CCW: to -x)
    ant = -d / np.linalg.norm(d)
    axis = max((("+y", (0, 1)), ("-y", (0, -1)), ("+x", (1, 0)), ("-x", (-1, 0))),
               key=lambda a: float(ant @ np.asarray(a[1])))[0]
    out.update(anterior=axis, angle_deg=ang)
    return out


_TURN = {"+y": 0, "-x": -90, "-y": 180, "+x": 90}  # rotation (deg, CCW about z) to bring it to +y


def load_mesh(path: str | os.PathLike, *, reorient: bool = False, tissue_map=None,
              units: str | None = None,
              facing: Literal["check", "reorient", "ignore"] = "check") -> TetMesh:
    """Read a TetMesh written by :func:`save_mesh` or by another tool.

    For ``.msh``, tissues come from the physical tags (``gmsh:physical``); if the file names its
    3D physical groups after tissues (BRAIN, CSF, SKULL, SCALP, any case, or other tools' names
    in `TISSUE_SYNONYMS`), tags are mapped through those names, so files numbering their groups
    differently load correctly. SimNIBS meshes (tags 1..10, no names) need
    ``tissue_map="simnibs"`` (`SIMNIBS_TISSUE_MAP`, plus where eyes, blood and muscle go).
    Gmsh 2.2, 4.0 and 4.1 files are read (meshio).

    ``.mat`` is jaxhead's layout (node, element, tissue; see `save_mesh`) or EIDORS's contributed
    head meshes: ``vtx`` (n, 3), ``tri`` or ``simp`` (m, 4) 1-based, ``materials.ref`` (m,) and
    ``materials.names`` (tissues mapped by name, `TISSUE_SYNONYMS`), MATLAB v5 or v7.3.
    Meshes from CUBIT (the seed paper's route: ``.unv`` -> MATLAB node / element / tissue) load
    once saved as that .mat layout.

    jaxhead works in RAS (x right, y anterior, z superior): electrodes are placed by name on
    that assumption. `head_facing` finds where the face points from the neck; a head facing
    elsewhere is an error (`facing="check"`) or is turned about z to face +y with a WARNING
    log naming the rotation (`facing="reorient"`); spheres and heads without a neck pass.

    Arguments:
        path: ``.msh``, ``.vtu`` or ``.mat``.
        reorient: fix negatively oriented tets by swapping two nodes (the count is logged);
            by default such a file is rejected.
        tissue_map: {file label or tissue name: "brain" | "csf" | "skull" | "scalp"} for labels
            the file does not name as ours, or "simnibs"; every label in the file must map.
        units: length unit of an EIDORS mesh's ``vtx`` ("mm", "cm", "m"); default mm, and a
            mesh smaller than 1 unit is an error asking for it.
        facing: "check" (default), "reorient" or "ignore" (see above).

    Returns:
        TetMesh with nodes (n_nodes, 3) mm, tets (n_tets, 4) 0-based, labels (n_tets,).
    """
    path = Path(path)
    ext = _ext(path, MESH_EXTENSIONS, "mesh")
    if facing not in ("check", "reorient", "ignore"):
        raise ValueError(f"`facing` = {facing!r}; use 'check', 'reorient' or 'ignore'.")
    if not path.is_file():
        raise FileNotFoundError(f"{str(path)!r}: no such file; check the path.")
    nodes, tets, labels = (_mesh_from_mat(path, tissue_map, units) if ext == ".mat"
                           else _mesh_from_meshio(path, ext, tissue_map))
    if reorient and nodes.ndim == 2 and nodes.shape[1] == 3 and tets.size:
        tets, n_flipped = orient_tets(nodes, tets)
        if n_flipped:
            log.info("%s: reoriented %d of %d tets", path, n_flipped, len(tets))
    try:
        mesh = TetMesh(nodes, tets, labels)
    except ValueError as e:
        hint = "" if reorient else " (pass reorient=True to fix the tets' orientation)"
        raise ValueError(f"{str(path)!r}: {e}{hint if 'oriented' in str(e) else ''}") from e
    if facing == "ignore":
        return mesh
    f = head_facing(mesh.nodes, mesh.tets)
    if f["anterior"] in (None, "+y"):
        if f["anterior"] is None:
            log.info("%s: facing direction undetermined (no neck offset from the cranium); RAS assumed", path)
        return mesh
    turn = _TURN[f["anterior"]]
    off = np.round(f["neck_offset_mm"], 1).tolist()
    if facing == "check":
        raise ValueError(
            f"{str(path)!r}: the head faces {f['anterior']} (its neck lies {off} mm (x, y) from "
            "the cranium's centre, behind the face), but jaxhead assumes RAS (face towards +y): "
            "named electrodes would land on the wrong side. Pass facing='reorient' to turn it "
            f"by {turn} deg about z (reported), or convert the file to RAS.")
    t = np.radians(turn)
    rot = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    log.warning("%s: the head faced %s; turned by %d deg about z to face +y (RAS). Node "
                "coordinates differ from the file's: x' = R x with R = %s.", path,
                f["anterior"], turn, np.round(rot, 6).tolist())
    return TetMesh(mesh.nodes @ rot.T, mesh.tets, mesh.labels)


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

