"""The TetGen backend of :func:`jaxhead.geometry.tetrahedralize`: constrained Delaunay.  [host]

TetGen (Si 2015, ACM TOMS 41:11; AGPL-3.0, an optional extra: ``pip install jaxhead[tetgen]``,
through the ``tetgen`` wheel) meshes the four nested surfaces as one piecewise linear complex
with a region seed (and a maximum tet volume) per shell: the input triangles are mesh faces, each
tet's tissue is its region's. Settings (measured on the 2 mm phantom's surfaces:
experiments/results/meshers.md): quality refinement at radius-edge ratio 1.5 with the surfaces
kept as given (``-Y``, ``nobisect``), since letting TetGen split surface triangles (no ``-Y``)
leaves many more slivers (its Steiner points on the surfaces); ten optimisation passes with flips
up to level 5 (``-O5/7``-like).

Sizing: TetGen's background-mesh sizing (``-m``) crashes the wheel (pyvista/tetgen#65), so the
refinement around refine points comes from the surfaces, refined there beforehand
(``jaxhead.geometry.refine``), and Delaunay refinement's grading away from them; each shell's
edge is a maximum tet volume per region (that of the regular tet of the edge).
"""

import numpy as np

from ..tissue import TISSUES

#: TetGen's quality bound (maximum radius-edge ratio, ``-q``) and optimisation settings (``-O``).
_MIN_RATIO = 1.5
_OPT = dict(opt_iterations=10, opt_max_flip_level=5, optmaxdihedral=160.0)


def mesh_tetgen(surfs, edges_mm, seeds):
    """Four-tissue tet mesh of the nested surfaces with TetGen.

    Arguments:
        surfs: [(vertices (n_k, 3) mm, faces (m_k, 3))] of the BRAIN, CSF, SKULL, SCALP
            surfaces: closed, outward, strictly nested (checked by the caller).
        edges_mm: four target edges (mm), BRAIN..SCALP.
        seeds: (4, 3) mm, a point strictly inside each shell (BRAIN..SCALP).

    Returns:
        (nodes (n, 3) mm, tets (m, 4) int64, labels (m,) int64 in 1..4).
    """
    import tetgen

    V = np.concatenate([np.asarray(s[0], dtype=np.float64) for s in surfs])
    offs = np.cumsum([0] + [len(s[0]) for s in surfs])[:-1]
    F = np.concatenate([np.asarray(s[1]) + o for s, o in zip(surfs, offs)]).astype(np.int32)
    tg = tetgen.TetGen(V, F)
    for k, t in enumerate(TISSUES):
        tg.add_region(int(t), [float(x) for x in seeds[k]], float(edges_mm[k] ** 3 / (6 * np.sqrt(2))))
    try:
        nodes, tets, attr, _ = tg.tetrahedralize(
            plc=True, quality=True, minratio=_MIN_RATIO, nobisect=True, regionattrib=True,
            varvolume=True, steinerleft=-1, quiet=True, **_OPT)
    except RuntimeError as e:
        raise RuntimeError(f"TetGen failed on the four surfaces: {e}") from e
    labels = np.rint(np.asarray(attr, dtype=np.float64).ravel()).astype(np.int64)
    return np.asarray(nodes, dtype=np.float64), np.asarray(tets, dtype=np.int64), labels
