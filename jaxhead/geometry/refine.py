"""Local refinement of a closed triangle surface by longest-edge bisection.  [host]

The constrained-Delaunay meshers (gmsh, TetGen) keep every input surface triangle as a mesh
face, so a mesh refined under the electrodes needs surfaces refined there first. An edge is
split at its midpoint when it is longer than `_SPLIT_FACTOR` times the target size at its
midpoint, and so is every edge on its longest-edge propagation path (the longest edge of each
triangle next to a split edge, in turn) that ends at a "terminal edge", the longest edge of both
its triangles (Rivara 1997, IJNME 40:3313); each pass splits the terminal edges. Every path ends
at a terminal edge, so each pass splits something while any edge is too long, each triangle is split at most once per pass (the passes vectorise), and
triangle angles stay bounded below (longest-edge bisection at most halves the smallest angle
once). Midpoints lie on the old triangles: the refined surface is the same polyhedron, so
nesting, gaps and enclosed volumes do not change.
"""

from collections.abc import Callable

import numpy as np

#: An edge is split when longer than this times the target size at its midpoint: the halves are
#: then at least 0.75 x the target, so the refined surface is neither coarser than 1.5 x nor
#: finer than 0.75 x the target.
_SPLIT_FACTOR = 1.5

#: At most this many bisection passes (each at least halves the longest too-long edges).
_MAX_PASSES = 40


def refine_surface(vertices: np.ndarray, faces: np.ndarray,
                   size_mm: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray, int]:
    """Bisect the surface's edges that are longer than 1.5 x the target size at their midpoint.

    Arguments:
        vertices: (n, 3) mm; faces: (m, 3) int, a closed manifold, consistently oriented.
        size_mm: maps (k, 3) points (mm) to the target edge length there (k,) mm; np.inf
            where no refinement is wanted.

    Returns:
        (vertices (n', 3), faces (m', 3), number of edges split). The first n vertices are the
        input's; faces keep the input's orientation.
    """
    V = np.array(vertices, dtype=np.float64, copy=True)
    F = np.array(faces, dtype=np.int64, copy=True)
    n_split = 0
    for _ in range(_MAX_PASSES):
        # Undirected edges, and for each face its three edge ids (local edge j joins j, j+1).
        e = np.sort(np.stack([F, np.roll(F, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
        uniq, eid = np.unique(e, axis=0, return_inverse=True)
        eid = eid.reshape(-1, 3)
        length = np.linalg.norm(V[uniq[:, 0]] - V[uniq[:, 1]], axis=1)
        mid = 0.5 * (V[uniq[:, 0]] + V[uniq[:, 1]])
        too_long = length > _SPLIT_FACTOR * np.asarray(size_mm(mid), dtype=np.float64)
        if not too_long.any():
            break
        # Each face's longest edge, ties broken by edge id so that the choice is deterministic.
        rank = np.lexsort((np.arange(len(uniq)), length))
        order = np.empty(len(uniq), dtype=np.int64)
        order[rank] = np.arange(len(uniq))
        local = np.argmax(order[eid], axis=1)
        longest = eid[np.arange(len(F)), local]
        # Terminal edges: the longest edge of every face they belong to (both, on a closed surface).
        n_faces = np.bincount(eid.ravel(), minlength=len(uniq))
        n_longest = np.bincount(longest, minlength=len(uniq))
        # A too-long edge that is not terminal needs the longest edges along its propagation path
        # split first, even where those are short enough for the target there (the target varies).
        need = too_long.copy()
        while True:
            grow = np.zeros(len(uniq), dtype=bool)
            grow[longest[need[eid].any(axis=1)]] = True
            if not (grow & ~need).any():
                break
            need |= grow
        split = need & (n_longest == n_faces)
        if not split.any():  # cannot happen on a closed manifold; guard against a malformed one
            break
        new_id = np.full(len(uniq), -1, dtype=np.int64)
        new_id[split] = len(V) + np.arange(int(split.sum()))
        V = np.concatenate([V, mid[split]])
        hit = split[longest]
        f, j = F[hit], local[hit]
        r = np.arange(len(f))
        a, b, c = f[r, j], f[r, (j + 1) % 3], f[r, (j + 2) % 3]
        m = new_id[longest[hit]]
        F = np.concatenate([F[~hit], np.stack([a, m, c], axis=1), np.stack([m, b, c], axis=1)])
        n_split += int(split.sum())
    return V, F, n_split
