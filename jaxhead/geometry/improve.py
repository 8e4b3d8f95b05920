"""Volume-mesh improvement that keeps labels and interfaces: node relocation, flips, splits.  [host]

fTetWild's interior tets are good; its poor tets sit on the interfaces (three or four nodes on a
meshed surface), where its envelope lets nodes lie anywhere within ~0.3 mm of the surface. This
module relocates the nodes of poor tets, one independent set at a time (no two nodes of a set
share a tet, so their moves do not interact):

- a node inside one tissue (not on an interface or the outer boundary) moves freely;
- a node on exactly one meshed surface slides along it: every candidate position is projected
  onto the *input* surface (closest point), so interfaces stay on their surfaces;
- a node on two or more surfaces stays.

Labels never change, and no tet may invert (every move must raise the worst quality of the
node's tets), so no tet ever straddles an interface.

Candidates for a node are the mean of the "ideal apex" positions over its tets (for each tet,
the apex that makes the opposite face a regular tet), the worst tet's ideal apex, and the mean
of the neighbouring nodes, each taken in steps of 1, 0.6, 0.3 and 0.12 of the move. A candidate
may neither lower the worst quality among the node's tets nor add a tet below the Table-2 limit,
and must improve one of the two (maximin alone raises the worst tet of a star while pushing its
neighbours below the limit: on a mesh of one-tet-thick shells it took 2315 tets below 0.2 to 2383;
with the count guarded, to 997); the best such candidate (fewest below the limit, then the best
worst) is taken. This is
optimisation-based smoothing of the worst element of the star with smart-Laplacian acceptance
(Freitag & Ollivier-Gooch 1997, IJNME 40:3979; Canann, Tristano & Staten 1998, 7th Int. Meshing
Roundtable), done on the host with vectorised candidate evaluation.

What relocation cannot mend (a cap whose nodes all sit on surfaces, a high-valence node
whose star is all poor) gets topological help between relocation cycles: 2-3 and 3-2 flips
(:func:`_flip_pass`), insertion of the poor tets' circumcentres with a local Delaunay cavity
(:func:`_insert_pass`: the fan of needles a constrained-Delaunay mesher leaves between a coarse
surface node and a finely refined surface across a thick shell) and, when neither helps, a
midpoint split of each poor tet's longest edge (:func:`_split_pass`), all inside one tissue so
that no interface face or label changes; the best state seen is kept, so the extra cycles never
leave a worse mesh.

A tet with all four nodes and all six edges on one surface (a one-tet-thick channel of CSF
between two folds of the brain surface) has no free node and no edge inside its tissue, so none
of the above can mend it; :func:`repair_stuck`, which the mesh stage runs only when the
improvement and its restarts leave tets below the limit, bisects such tets' longest edges,
surface edges included (:func:`split_edges`: new surface nodes lie on their input surface), and
improves the piece of mesh around them again.

Quality is Verdict's (``jaxhead.geometry.quality``): q = min(scaled Jacobian, 0.6 / condition number),
which puts both of the seed paper's limits (scaled Jacobian 0.2, condition number 3) at q = 0.2.
"""

import time

import numpy as np

from .tetmesh import _TET_FACES, face_adjacency, signed_volumes

#: The seed paper's Table-2 limit (scaled Jacobian 0.2, condition number 3) in terms of q.
LIMIT = 0.2

#: Flip/split cycles in a row that may fail to improve the best state before the improvement stops.
_PATIENCE = 3

#: Quality below which a tet's nodes are relocated: a margin above the Table-2 limit.
TARGET_QUALITY = 0.22

_STEPS = np.array([1.0, 0.6, 0.3, 0.12])


def tet_quality(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """min(scaled Jacobian, 0.6 / condition number) per tet; <= 0 for inverted or flat tets.

    Arguments:
        nodes: (n, 3) mm; tets: (m, 4) node indices.

    Returns:
        (m,) float64; 0.2 is the seed paper's acceptance limit for both metrics.
    """
    sj, cond = _sj_cond(nodes[tets])
    return np.where(sj > 0, np.minimum(sj, 0.6 / np.where(cond > 0, cond, np.inf)), sj)


def _sj_cond(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scaled Jacobian and condition number of tets with corners p (m, 4, 3).

    Verdict's definitions, as ``jaxhead.geometry.quality`` computes them (the tests check that
    they agree), in NumPy: the improvement step evaluates a few thousand candidate tets at a
    time, where a jit-compiled call costs more in dispatch and padding than the arithmetic.
    """
    p = np.asarray(p, dtype=np.float64)
    p0, p1, p2, p3 = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
    l0, l1, l2 = p1 - p0, p2 - p1, p0 - p2
    l3, l4, l5 = p3 - p0, p3 - p1, p3 - p2
    sq = [np.einsum("ij,ij->i", v, v) for v in (l0, l1, l2, l3, l4, l5)]
    jac = np.einsum("ij,ij->i", np.cross(l2, l0), l3)
    corner = np.maximum(np.maximum(sq[0] * sq[2] * sq[3], sq[0] * sq[1] * sq[4]),
                        np.maximum(sq[1] * sq[2] * sq[5], sq[3] * sq[4] * sq[5]))
    length_product = np.maximum(np.sqrt(corner), np.abs(jac))
    sj = np.sqrt(2.0) * jac / np.where(length_product > 0, length_product, 1.0)
    sj[length_product == 0] = 0.0
    # S = A W^-1 with the regular tet as the target: columns c1..c3.
    c1 = l0
    c2 = (-2.0 * l2 - l0) / np.sqrt(3.0)
    c3 = (3.0 * l3 + l2 - l0) / np.sqrt(6.0)
    frob2 = sum(np.einsum("ij,ij->i", c, c) for c in (c1, c2, c3))
    c23 = np.cross(c2, c3)
    adj2 = sum(np.einsum("ij,ij->i", c, c) for c in (np.cross(c1, c2), c23, np.cross(c1, c3)))
    det_s = np.einsum("ij,ij->i", c1, c23)
    cond = np.full(len(p), np.inf)
    nz = det_s != 0
    cond[nz] = np.sqrt(frob2[nz] * adj2[nz]) / (3.0 * det_s[nz])
    return sj, cond


def _ranges(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """The concatenation of arange(s, e) over the pairs, without a Python loop."""
    counts = ends - starts
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    first = np.cumsum(counts) - counts
    return np.arange(total) - np.repeat(first - starts, counts)


def _incidence(tets: np.ndarray, n_nodes: int):
    """CSR node -> (tet, local corner) incidence: ptr (n+1,), tet (4m,), corner (4m,)."""
    n = tets.ravel()
    order = np.argsort(n, kind="stable")
    ptr = np.zeros(n_nodes + 1, dtype=np.int64)
    np.add.at(ptr, n + 1, 1)
    return np.cumsum(ptr), (np.arange(4 * len(tets)) // 4)[order], (np.arange(4 * len(tets)) % 4)[order]


def classify_nodes(tets: np.ndarray, labels: np.ndarray, n_nodes: int) -> np.ndarray:
    """Which meshed surface each node lies on.

    Surface k (0..3: BRAIN, CSF, SKULL, SCALP) separates tets labelled <= k+1 from the rest;
    the outer boundary belongs to SCALP.

    Returns:
        (n_nodes,) int: -1 free (inside one tissue), k on surface k only, -2 on several.
    """
    faces, owner, fi, fj, boundary = face_adjacency(tets)
    la, lb = labels[owner[fi]], labels[owner[fj]]
    on = np.zeros((4, n_nodes), dtype=bool)
    for k in range(4):
        on[k, faces[fi[(la <= k + 1) != (lb <= k + 1)]].ravel()] = True
    on[3, faces[boundary].ravel()] = True
    n_on = on.sum(axis=0)
    return np.where(n_on == 0, -1, np.where(n_on > 1, -2, np.argmax(on, axis=0)))


def _independent(cand: np.ndarray, tets: np.ndarray, ptr, inc_t, rng) -> np.ndarray:
    """A subset of `cand` nodes no two of which share a tet (Luby's random priorities)."""
    prio = np.full(ptr.shape[0] - 1, -1.0)
    prio[cand] = rng.random(len(cand))
    starts, ends = ptr[cand], ptr[cand + 1]
    seg = np.repeat(np.arange(len(cand)), ends - starts)
    # Only the candidates' own tets matter: a node wins when it has the top priority in each.
    tet_max = prio[tets[inc_t[_ranges(starts, ends)]]].max(axis=1)
    lost = np.bincount(seg, weights=tet_max != prio[cand][seg], minlength=len(cand))
    return cand[lost == 0]


def _relocate(nodes, tets, q, sel, cls, ptr, inc_t, inc_c, project, rng=None, n_random: int = 0) -> int:
    """Try candidate positions for the independent nodes `sel`; apply improving moves. In place.

    With `n_random` > 0, each node also tries that many random positions in a ball around it
    (radius half its star's mean edge; `rng` draws them): a random local search for the stars
    that none of the three targets improves (see :func:`improve_mesh`'s `random_candidates`)."""
    starts, ends = ptr[sel], ptr[sel + 1]
    counts = ends - starts
    seg = np.repeat(np.arange(len(sel)), counts)
    flat = _ranges(starts, ends)
    st, sc = inc_t[flat], inc_c[flat]  # star tets and the node's corner in each
    # Opposite face of the node's corner, outward from the tet (away from the node).
    face = tets[st[:, None], _TET_FACES[sc]]
    fp = nodes[face]
    n = np.cross(fp[:, 1] - fp[:, 0], fp[:, 2] - fp[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    edge = (np.linalg.norm(fp[:, 1] - fp[:, 0], axis=1) + np.linalg.norm(fp[:, 2] - fp[:, 1], axis=1)
            + np.linalg.norm(fp[:, 0] - fp[:, 2], axis=1)) / 3
    apex = fp.mean(axis=1) - n * (np.sqrt(2.0 / 3.0) * edge)[:, None]
    x = nodes[sel]
    mean_apex = np.zeros_like(x)
    np.add.at(mean_apex, seg, apex)
    mean_apex /= counts[:, None]
    mean_nb = np.zeros_like(x)
    np.add.at(mean_nb, seg, fp.mean(axis=1))
    mean_nb /= counts[:, None]
    qs = q[st]
    q_old = np.full(len(sel), np.inf)
    np.minimum.at(q_old, seg, qs)
    worst = np.full(len(sel), -1)
    is_worst = qs == q_old[seg]
    worst[seg[is_worst]] = np.nonzero(is_worst)[0]
    targets = np.stack([mean_apex, apex[worst], mean_nb], axis=1)  # (s, 3, 3)
    cand = x[:, None, None] + _STEPS[None, None, :, None] * (targets[:, :, None] - x[:, None, None])
    cand = cand.reshape(len(sel), -1, 3)  # (s, c, 3)
    if n_random:
        star_edge = np.zeros(len(sel))
        np.add.at(star_edge, seg, edge)
        radius = 0.5 * star_edge / counts
        u = rng.standard_normal((len(sel), n_random, 3))
        u *= (rng.random((len(sel), n_random, 1)) ** (1 / 3)) / np.linalg.norm(u, axis=2, keepdims=True)
        cand = np.concatenate([cand, x[:, None] + radius[:, None, None] * u], axis=1)
    n_c = cand.shape[1]
    for k, proj in enumerate(project):
        on_k = cls[sel] == k
        if on_k.any():
            cand[on_k] = proj(cand[on_k].reshape(-1, 3)).reshape(-1, n_c, 3)
    # Quality of every star tet with the node at every candidate position.
    p = np.repeat(nodes[tets[st]][:, None], n_c, axis=1)  # (t, c, 4, 3)
    p[np.arange(len(st)), :, sc] = cand[seg]
    q_new = tet_quality_corners(p.reshape(-1, 4, 3)).reshape(len(st), n_c)
    q_min = np.full((len(sel), n_c), np.inf)
    np.minimum.at(q_min, seg, q_new)
    # A move may neither lower the star's worst tet nor add a tet below the Table-2 limit, and
    # must improve one of the two; of those, the fewest tets below the limit, then the best worst.
    n_old = np.bincount(seg, weights=qs < LIMIT, minlength=len(sel))
    n_new = np.zeros((len(sel), n_c))
    np.add.at(n_new, seg, q_new < LIMIT)
    ok = (q_min >= q_old[:, None]) & (n_new <= n_old[:, None]) & (
        (n_new < n_old[:, None]) | (q_min > q_old[:, None] + 1e-12))
    best = np.argmax(np.where(ok, q_min - 2.0 * n_new, -np.inf), axis=1)  # q_min lies in (0, 1]
    gain = ok[np.arange(len(sel)), best]
    if not gain.any():
        return 0
    nodes[sel[gain]] = cand[np.nonzero(gain)[0], best[gain]]
    upd = gain[seg]
    q[st[upd]] = q_new[np.nonzero(upd)[0], best[seg[upd]]]
    return int(gain.sum())


def _flip_pass(nodes, tets, labels, q, target):
    """One pass of 2-3 and 3-2 flips around the tets below `target`, inside one tissue.

    A 2-3 flip replaces two tets sharing a face (a, b, c) by three around the edge joining their
    apexes p, r; a 3-2 flip replaces the three tets around an edge (i, j) by two sharing the
    triangle of the ring (x, y, z). Both keep the outer faces of the cavity, so when all the
    tets involved carry one label no interface face and no label changes, and no node moves.
    A flip is valid when the new tets fill the cavity: p-r crosses the face (the three new
    volumes share one sign), or i and j lie on opposite sides of the ring's plane (with a
    closed ring of three positive tets this means i-j crosses the triangle). It is taken when
    it raises the cavity's worst quality; flips sharing a tet are taken best first, one each.
    (Klingner & Shewchuk 2007, "Aggressive tetrahedral mesh improvement", 16th IMR.)

    Returns:
        (tets, labels, q) updated, and the numbers of 2-3 and 3-2 flips taken.
    """


    m = len(tets)
    faces, owner, fi, fj, _ = face_adjacency(tets)
    nbr = np.full(4 * m, -1)
    nbr[fi], nbr[fj] = owner[fj], owner[fi]
    nbr = nbr.reshape(m, 4)  # neighbour across face k (the face opposite corner k)
    poor = np.nonzero(q < target)[0]
    old_sets, new_sets, kinds = [], [], []

    # 2-3 flips through each face of each poor tet.
    t = np.repeat(poor, 4)
    k = np.tile(np.arange(4), len(poor))
    u = nbr[t, k]
    ok = u >= 0
    t, k, u = t[ok], k[ok], u[ok]
    ok = (labels[u] == labels[t]) & ((t < u) | (q[u] >= target))  # each poor pair once
    t, k, u = t[ok], k[ok], u[ok]
    face = tets[t[:, None], _TET_FACES[k]]  # (f, 3)
    p = tets[t, k]
    r = tets[u].sum(axis=1) - face.sum(axis=1)
    new = np.stack([np.stack([face[:, e], face[:, (e + 1) % 3], p, r], axis=1) for e in range(3)],
                   axis=1)  # (f, 3, 4)
    if len(new):
        vol = signed_volumes(nodes, new.reshape(-1, 4)).reshape(-1, 3)
        same = np.all(vol > 0, axis=1) | np.all(vol < 0, axis=1)
        neg = vol < 0
        new[neg, 2], new[neg, 3] = new[neg, 3].copy(), new[neg, 2].copy()
        for a in np.nonzero(same)[0]:
            old_sets.append((t[a], u[a]))
            new_sets.append(new[a])
            kinds.append(23)

    # 3-2 flips of each edge of each poor tet that has exactly three tets around it.
    ptr, inc_t, _ = _incidence(tets, len(nodes))
    seen = set()
    for ti in poor:
        for a in range(4):
            for b in range(a + 1, 4):
                i, j = int(tets[ti, a]), int(tets[ti, b])
                if (min(i, j), max(i, j)) in seen:
                    continue
                seen.add((min(i, j), max(i, j)))
                star = np.intersect1d(inc_t[ptr[i]:ptr[i + 1]], inc_t[ptr[j]:ptr[j + 1]])
                if len(star) != 3 or np.any(labels[star] != labels[ti]):
                    continue
                ring, counts = np.unique(tets[star][(tets[star] != i) & (tets[star] != j)],
                                         return_counts=True)
                if len(ring) != 3 or np.any(counts != 2):
                    continue  # the edge is on the boundary: its ring is open
                two = np.array([[*ring, i], [*ring, j]])
                vol = signed_volumes(nodes, two)
                if not vol[0] * vol[1] < 0:
                    continue
                two[vol < 0, 2], two[vol < 0, 3] = two[vol < 0, 3].copy(), two[vol < 0, 2].copy()
                old_sets.append(tuple(star))
                new_sets.append(two)
                kinds.append(32)
    if not old_sets:
        return tets, labels, q, 0, 0

    sizes = np.array([len(n) for n in new_sets])
    q_new_all = tet_quality(nodes, np.concatenate(new_sets))
    q_new = np.minimum.reduceat(q_new_all, np.cumsum(sizes) - sizes)
    q_old = np.array([q[list(o)].min() for o in old_sets])
    gain = q_new - q_old
    used = np.zeros(m, dtype=bool)
    drop, add, add_q, add_label = [], [], [], []
    n23 = n32 = 0
    offs = np.cumsum(sizes) - sizes
    for c in np.argsort(-gain):
        if gain[c] <= 1e-9:
            break
        o = list(old_sets[c])
        if used[o].any():
            continue
        used[o] = True
        drop.extend(o)
        add.append(new_sets[c])
        add_q.append(q_new_all[offs[c]:offs[c] + sizes[c]])
        add_label.append(np.full(sizes[c], labels[o[0]]))
        n23 += kinds[c] == 23
        n32 += kinds[c] == 32
    if not drop:
        return tets, labels, q, 0, 0
    keep = np.ones(m, dtype=bool)
    keep[drop] = False
    tets = np.concatenate([tets[keep]] + add)
    labels = np.concatenate([labels[keep]] + add_label)
    q = np.concatenate([q[keep]] + add_q)
    return tets, labels, q, n23, n32


def _split_pass(nodes, tets, labels, q, target):
    """Split, at its midpoint, the longest edge inside one tissue of each tet below `target`.

    For a tet that neither relocation nor flips can mend (typically a small face on a finely
    meshed surface with an apex far inside: too steep a size gradient, many such tets around
    one node), a node in the middle of its long edge lets the next relocation rounds shape the
    tets. Only edges whose closed ring of tets carries one label are split (the new node lies
    inside that tissue; no interface or label changes); edges sharing a tet are split best
    (longest) first, one each. Each tet (i, j, x, y) around edge (i, j) becomes (m, j, x, y)
    and (i, m, x, y), both positive.

    Returns:
        (nodes, tets, labels, q) updated, and the number of edges split.
    """
    ptr, inc_t, _ = _incidence(tets, len(nodes))
    pairs = [(a, b) for a in range(4) for b in range(a + 1, 4)]
    chosen, used = [], np.zeros(len(tets), dtype=bool)
    poor = np.nonzero(q < target)[0]
    for ti in poor[np.argsort(q[poor])]:
        e = tets[ti][np.array(pairs)]
        length = np.linalg.norm(nodes[e[:, 0]] - nodes[e[:, 1]], axis=1)
        for c in np.argsort(-length):
            i, j = int(e[c, 0]), int(e[c, 1])
            star = np.intersect1d(inc_t[ptr[i]:ptr[i + 1]], inc_t[ptr[j]:ptr[j + 1]])
            if used[star].any() or np.any(labels[star] != labels[ti]):
                continue
            _, counts = np.unique(tets[star][(tets[star] != i) & (tets[star] != j)],
                                  return_counts=True)
            if np.any(counts != 2):
                continue  # on the boundary: the ring is open
            used[star] = True
            chosen.append((i, j, star))
            break
    if not chosen:
        return nodes, tets, labels, q, 0
    mid = np.array([(nodes[i] + nodes[j]) / 2 for i, j, _ in chosen])
    first = len(nodes)
    nodes = np.concatenate([nodes, mid])
    drop = np.concatenate([star for _, _, star in chosen])
    add = []
    for c, (i, j, star) in enumerate(chosen):
        for a, b in ((i, j), (j, i)):
            t = tets[star].copy()
            t[t == a] = first + c
            add.append(t)
    add = np.concatenate(add)
    add_label = np.concatenate([np.tile(labels[star], 2) for _, _, star in chosen])
    keep = np.ones(len(tets), dtype=bool)
    keep[drop] = False
    tets = np.concatenate([tets[keep], add])
    labels = np.concatenate([labels[keep], add_label])
    q = np.concatenate([q[keep], tet_quality(nodes, add)])
    return nodes, tets, labels, q, len(chosen)


def split_edges(nodes: np.ndarray, tets: np.ndarray, labels: np.ndarray, edges, points=None):
    """Split each edge (i, j) at a point on it: every tet around the edge becomes two.

    A tet (i, j, x, y) around the edge becomes (m, j, x, y) and (i, m, x, y), both with its label
    (m: the new node). With m strictly between i and j both halves keep the tet's orientation
    and split its volume in the ratio of the edge's two parts, so every tissue's volume and
    region is kept exactly; a face (i, j, x) becomes the two halves (m, j, x), (i, m, x) of the
    same triangle, and every face without the edge stays. Any edge may be split: inside one
    tissue (m is then inside it), on an interface (the surface triangles through the edge are
    halved and m lies on the meshed surface) or on the outer boundary (an open ring). This is
    the bisection step of longest-edge refinement (Rivara 1997, "New longest-edge algorithms
    for the refinement and/or improvement of unstructured triangulations", IJNME 40:3313).

    Arguments:
        nodes: (n, 3) mm; tets: (m, 4) positively oriented; labels: (m,).
        edges: (k, 2) node indices, each an edge of the mesh; no two edges in one tet.
        points: (k, 3) positions of the new nodes, or None for the edges' midpoints. A point
            off the open segment may invert tets; that is the caller's to check.

    Returns:
        (nodes (n + k, 3) with the new nodes appended in the order of `edges`, tets, labels):
        the tets around no edge first, in their order, then the halves.

    Raises:
        ValueError: `edges` not (k, 2) node indices, a pair that is not an edge of the mesh, or
            two edges in one tet (split those in two calls).
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    tets, labels = np.asarray(tets), np.asarray(labels)
    edges = np.asarray(edges)
    if edges.ndim != 2 or edges.shape[1] != 2 or not np.issubdtype(edges.dtype, np.integer) or (
            len(edges) and (edges.min() < 0 or edges.max() >= len(nodes))):
        raise ValueError(f"`edges` must be (k, 2) node indices in [0, {len(nodes)}), got shape "
                         f"{edges.shape}, dtype {edges.dtype}.")
    if points is None:
        points = 0.5 * (nodes[edges[:, 0]] + nodes[edges[:, 1]])
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (len(edges), 3):
        raise ValueError(f"`points` must be ({len(edges)}, 3) or None (midpoints), got shape {points.shape}.")
    ptr, inc_t, _ = _incidence(tets, len(nodes))
    stars = []
    used = np.zeros(len(tets), dtype=bool)
    for i, j in edges.tolist():
        star = np.intersect1d(inc_t[ptr[i]:ptr[i + 1]], inc_t[ptr[j]:ptr[j + 1]])
        if i == j or not len(star):
            raise ValueError(f"`edges` holds ({i}, {j}), which is not an edge of the mesh; pass "
                             "pairs of nodes that share a tet.")
        if used[star].any():
            raise ValueError(f"edge ({i}, {j}) shares a tet with an earlier edge of `edges`; split "
                             "edges of one tet in separate calls.")
        used[star] = True
        stars.append(star)
    add, add_label = [], []
    for c, ((i, j), star) in enumerate(zip(edges.tolist(), stars)):
        for a in (i, j):
            t = tets[star].copy()
            t[t == a] = len(nodes) + c
            add.append(t)
            add_label.append(labels[star])
    if not add:
        return nodes.copy(), tets.copy(), labels.copy()
    return (np.concatenate([nodes, points]), np.concatenate([tets[~used]] + add),
            np.concatenate([labels[~used]] + add_label))


def _bisect_pass(nodes, tets, labels, q, fixed, project):
    """Split the longest edge (surface edges included) of each tet below the limit, worst first,
    one edge per tet and no two in one tet, each with at least one end not `fixed`; a new node
    on one surface goes onto that input surface (`project`) when its tets stay positive there.

    Returns:
        (nodes, tets, labels, q) updated, the number of edges split, and how many of those lay
        on an interface or the boundary.
    """
    ptr, inc_t, _ = _incidence(tets, len(nodes))
    pairs = np.array([(a, b) for a in range(4) for b in range(a + 1, 4)])
    chosen, used = [], np.zeros(len(tets), dtype=bool)
    poor = np.nonzero(q < LIMIT)[0]
    for ti in poor[np.argsort(q[poor], kind="stable")]:
        e = tets[ti][pairs]
        length = np.linalg.norm(nodes[e[:, 0]] - nodes[e[:, 1]], axis=1)
        for c in np.argsort(-length, kind="stable"):
            i, j = int(e[c, 0]), int(e[c, 1])
            if fixed[i] and fixed[j]:
                continue
            star = np.intersect1d(inc_t[ptr[i]:ptr[i + 1]], inc_t[ptr[j]:ptr[j + 1]])
            if used[star].any():
                continue
            used[star] = True
            chosen.append((i, j))
            break
    if not chosen:
        return nodes, tets, labels, q, 0, 0
    n0 = len(nodes)
    nodes, tets, labels = split_edges(nodes, tets, labels, np.array(chosen))
    cls = classify_nodes(tets, labels, len(nodes))[n0:]
    if (cls >= 0).any():
        ptr, inc_t, inc_c = _incidence(tets, len(nodes))
        for c in np.nonzero(cls >= 0)[0]:
            x = n0 + c
            y = project[cls[c]](nodes[x][None])[0]
            star = inc_t[ptr[x]:ptr[x + 1]]
            p = nodes[tets[star]]
            p[np.arange(len(star)), inc_c[ptr[x]:ptr[x + 1]]] = y
            if np.all(signed_volumes(p.reshape(-1, 3), np.arange(4 * len(star)).reshape(-1, 4)) > 0):
                nodes[x] = y
    return nodes, tets, labels, tet_quality(nodes, tets), len(chosen), int((cls != -1).sum())


def _circumspheres(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Circumcentres (m, 3) and squared circumradii (m,) of tets; inf for flat ones."""
    p = nodes[tets]
    a = p[:, 1:] - p[:, :1]  # (m, 3, 3)
    rhs = 0.5 * np.einsum("mij,mij->mi", a, a)
    det = np.linalg.det(a)
    ok = np.abs(det) > 1e-12 * np.maximum(np.einsum("mij,mij->m", a, a), 1e-300) ** 1.5
    c = np.full((len(tets), 3), np.inf)
    if ok.any():
        c[ok] = p[ok, 0] + np.linalg.solve(a[ok], rhs[ok][..., None])[..., 0]
    r2 = np.where(ok, np.einsum("ij,ij->i", c - p[:, 0], c - p[:, 0]), np.inf)
    return c, r2


def _locate(nodes, tets, labels, nbr, start: int, x: np.ndarray, max_steps: int = 64) -> int:
    """The tet of `start`'s tissue that contains x, by a visibility walk through faces inside that
    tissue; -1 when the walk meets an interface, the boundary, or does not end."""
    t = start
    for _ in range(max_steps):
        p = nodes[tets[t]]
        # Signed volume of x with each face (face k opposite corner k, outward): x is beyond face k
        # when the tet (face k reversed, x) is negative.
        f = p[_TET_FACES]  # (4, 3, 3)
        vol = np.einsum("ij,ij->i", np.cross(f[:, 2] - f[:, 0], f[:, 1] - f[:, 0]), x - f[:, 0])
        k = int(np.argmin(vol))
        if vol[k] >= 0:
            return t
        u = nbr[t, k]
        if u < 0 or labels[u] != labels[t]:
            return -1
        t = int(u)
    return -1


def _insert_pass(nodes, tets, labels, q, target):
    """Insert a node at the circumcentre of each tet below `target` (Delaunay refinement), inside
    its own tissue, re-triangulating the cavity of tets whose circumspheres contain it.

    Needles and caps around a high-valence node (a node on a coarse surface facing a finely
    meshed one across a thick shell, with a fan of long edges a mesher left without interior
    nodes) are mended neither by moving nodes nor by flips; inserting circumcentres is how
    Delaunay refinement removes tets with a large circumradius-to-edge ratio (Shewchuk 1998,
    "Tetrahedral mesh generation by Delaunay refinement", 14th SoCG). The cavity is grown from the
    tet containing the point through faces inside one tissue only, so no interface face, label
    or tissue volume changes; it is shrunk until every new tet (a cavity face and the point) is
    positive and the new tets fill exactly the cavity's volume (a star-shaped cavity). A point
    outside its tissue (circumcentre beyond an interface) falls back to points on the way to it
    from the centroid (half, a quarter), the centroid, and a point towards the longest edge; the
    first whose insertion raises the cavity's worst quality (and adds no tet below the limit) is
    taken. Cavities do not overlap.

    Returns:
        (nodes, tets, labels, q) updated, and the number of nodes inserted.
    """
    m = len(tets)
    faces, owner, fi, fj, _ = face_adjacency(tets)
    nbr = np.full(4 * m, -1)
    nbr[fi], nbr[fj] = owner[fj], owner[fi]
    nbr = nbr.reshape(m, 4)
    poor = np.nonzero(q < target)[0]
    if not len(poor):
        return nodes, tets, labels, q, 0
    cen, r2 = _circumspheres(nodes, tets)
    used = np.zeros(m, dtype=bool)
    new_nodes, drop, add, add_label = [], [], [], []
    for t in poor[np.argsort(q[poor])]:
        if used[t]:
            continue
        best = None
        p = nodes[tets[t]]
        g = p.mean(axis=0)
        e = max(((a, b) for a in range(4) for b in range(a + 1, 4)),
                key=lambda ab: np.linalg.norm(p[ab[0]] - p[ab[1]]))
        mid = 0.5 * (p[e[0]] + p[e[1]])
        # The circumcentre; points towards it from the centroid (when it lies beyond the tissue);
        # the centroid; and a point towards the longest edge (for a cap whose circumcentre is far).
        cand = [cen[t]] + [g + f * (cen[t] - g) for f in (0.5, 0.25)] + [g, g + 0.6 * (mid - g)]
        for x in cand:
            if not np.all(np.isfinite(x)):
                continue
            c0 = _locate(nodes, tets, labels, nbr, int(t), x)
            if c0 < 0 or used[c0]:
                continue
            cav = _cavity(nodes, tets, labels, nbr, cen, r2, used, c0, x)
            if cav is None:
                continue
            cells, new = cav
            q_new = tet_quality(np.concatenate([nodes, x[None]]), new)
            if q_new.min() > q[cells].min() + 1e-9 and (q_new < LIMIT).sum() <= (q[cells] < LIMIT).sum():
                best = (cells, new, x)
                break
        if best is None:
            continue
        cells, new, x = best
        used[cells] = True
        idx = len(nodes) + len(new_nodes)
        new = np.where(new == len(nodes), idx, new)
        new_nodes.append(x)
        drop.append(cells)
        add.append(new)
        add_label.append(np.full(len(new), labels[cells[0]]))
    if not new_nodes:
        return nodes, tets, labels, q, 0
    nodes = np.concatenate([nodes, np.array(new_nodes)])
    keep = np.ones(m, dtype=bool)
    keep[np.concatenate(drop)] = False
    add = np.concatenate(add)
    tets = np.concatenate([tets[keep], add])
    labels = np.concatenate([labels[keep], np.concatenate(add_label)])
    q = np.concatenate([q[keep], tet_quality(nodes, add)])
    return nodes, tets, labels, q, len(new_nodes)


def _cavity(nodes, tets, labels, nbr, cen, r2, used, c0: int, x: np.ndarray, max_cells: int = 256):
    """Cells of `c0`'s tissue connected to it whose circumspheres contain x, shrunk to a cavity
    star-shaped from x. Returns (cells, new tets with x as node index len(nodes)) or None."""
    lab = labels[c0]
    cells, front = {c0}, [c0]
    while front and len(cells) < max_cells:
        nxt = []
        for c in front:
            for u in nbr[c]:
                u = int(u)
                if u < 0 or u in cells or used[u] or labels[u] != lab:
                    continue
                d = cen[u] - x
                if d @ d < r2[u] * (1 - 1e-9):
                    cells.add(u)
                    nxt.append(u)
        front = nxt
    xi = len(nodes)
    allp = np.concatenate([nodes, x[None]])
    for _ in range(64):
        cl = np.fromiter(cells, dtype=np.int64)
        f = tets[cl][:, _TET_FACES].reshape(-1, 3)  # outward faces of the cavity cells
        fo = np.repeat(cl, 4)
        nb = nbr[cl].reshape(-1)
        outer = ~np.isin(nb, cl)
        f, fo = f[outer], fo[outer]
        new = np.concatenate([f[:, [0, 2, 1]], np.full((len(f), 1), xi)], axis=1)
        vol = signed_volumes(allp, new)
        scale = np.abs(signed_volumes(nodes, tets[cl])).max()
        bad = vol <= 1e-9 * scale
        if not bad.any():
            if abs(vol.sum() - signed_volumes(nodes, tets[cl]).sum()) > 1e-9 * max(vol.sum(), 1e-300) * len(cl):
                return None
            return cl, new
        drop = set(fo[bad].tolist())
        if c0 in drop:
            return None
        cells -= drop
        # keep the part still connected to c0
        keep, front = {c0}, [c0]
        while front:
            nxt = []
            for c in front:
                for u in nbr[c]:
                    u = int(u)
                    if u in cells and u not in keep:
                        keep.add(u)
                        nxt.append(u)
            front = nxt
        cells = keep
    return None


def tet_quality_corners(p: np.ndarray) -> np.ndarray:
    """:func:`tet_quality` of tets given by their corners p (m, 4, 3)."""
    sj, cond = _sj_cond(p)
    return np.where(sj > 0, np.minimum(sj, 0.6 / np.where(cond > 0, cond, np.inf)), sj)


def improve_mesh(nodes: np.ndarray, tets: np.ndarray, labels: np.ndarray, project, *,
                 iterations: int = 10, target: float = TARGET_QUALITY, seed: int = 0,
                 flip_cycles: int = 6, random_candidates: int = 0, fixed: np.ndarray | None = None):
    """Improve the tets with quality below `target`, keeping interfaces on their surfaces.

    Node relocation (rounds over the poor tets' nodes) alternates with a pass of 2-3 / 3-2 flips
    inside each tissue (:func:`_flip_pass`) and one of circumcentre insertions
    (:func:`_insert_pass`) for the tets relocation cannot mend (a sliver whose nodes all sit on
    surfaces, one locked by its neighbours, a fan of needles around one node), and edge splits
    (:func:`_split_pass`) when neither changes anything; it stops when no tet is below the
    target or a cycle changes nothing.

    Arguments:
        nodes: (n, 3) mm; tets: (m, 4) positively oriented; labels: (m,) tissue 1..4.
        project: four callables (BRAIN, CSF, SKULL, SCALP surfaces) mapping (k, 3) points to
            their closest points on that input surface.
        iterations: rounds of relocation per cycle.
        target: quality (see :func:`tet_quality`) below which a tet is improved.
        seed: random priorities of the independent sets (results depend on it only slightly).
        flip_cycles: at most this many flip passes (each followed by relocation rounds).
        random_candidates: random positions tried per node per relocation besides the three
            targets (in a ball of half the star's mean edge). The targets come from the star's
            tets one at a time and can all miss a position that raises the star's worst tet:
            on the 2 mm skull_hole case three CSF tets stayed at q 0.187-0.189 through ten
            restarts while a random search found a position of one free node giving its star
            0.27. 0 (the default) keeps the step deterministic in the targets alone; the mesh
            stage's restarts use it.
        fixed: (n,) bool, nodes that never move (besides those on two surfaces), or None: the
            border of a piece cut out of a larger mesh (:func:`repair_stuck`), which must stay
            where the rest of the mesh meets it. Nodes the step adds are free.

    Returns:
        (nodes (n, 3), tets (m', 4), labels (m',), stats dict: poor tets before/after, the
        input's Table-2 counts (scaled Jacobian < 0.2, condition > 3), nodes moved, flips,
        nodes inserted, edges split, seconds). The tets change only by flips, insertions and
        splits within one tissue, so every tissue's region and every interface are those of the
        input.
    """
    t0 = time.perf_counter()
    nodes = np.array(nodes, dtype=np.float64, copy=True)
    tets = np.asarray(tets)
    labels = np.asarray(labels)
    n = len(nodes)
    if fixed is not None:
        fixed = np.asarray(fixed, dtype=bool)
        if fixed.shape != (n,):
            raise ValueError(f"`fixed` must be a bool mask of the {n} nodes, got shape {fixed.shape}.")
    rng = np.random.default_rng(seed)
    sj, cond = _sj_cond(nodes[tets])
    q = np.where(sj > 0, np.minimum(sj, 0.6 / np.where(cond > 0, cond, np.inf)), sj)
    below_before = int((q < LIMIT).sum())
    # The input's Table-2 counts (Vonach et al. 2012: scaled Jacobian 0.2-1, condition 1-3).
    table2_before = (int((sj < 0.2).sum()), int((cond > 3).sum()))
    min_before = float(q.min())
    moved = rounds = n23 = n32 = n_split = n_insert = 0
    # Relocation raises each star's worst tet but may push others below 0.2, and splits can leave
    # a worse mesh than the cycle before: keep the best state by the Table-2 count, then the
    # worst quality, starting from the input; stop after _PATIENCE cycles without a better one.
    best = ((below_before, -min_before), nodes.copy(), tets, labels, q.copy())
    stale = 0
    for cycle in range(flip_cycles + 1):
        if fixed is not None and len(fixed) < n:  # nodes added by insertions and splits are free
            fixed = np.concatenate([fixed, np.zeros(n - len(fixed), dtype=bool)])
        ptr, inc_t, inc_c = _incidence(tets, n)
        cls = classify_nodes(tets, labels, n)
        for _ in range(iterations):
            poor = q < target
            if not poor.any():
                break
            rounds += 1
            todo = np.unique(tets[poor])
            todo = todo[cls[todo] != -2]
            if fixed is not None:
                todo = todo[~fixed[todo]]
            moved_round = 0
            while len(todo):
                sel = _independent(todo, tets, ptr, inc_t, rng)
                moved_round += _relocate(nodes, tets, q, sel, cls, ptr, inc_t, inc_c, project,
                                         rng, random_candidates)
                todo = np.setdiff1d(todo, sel, assume_unique=True)
            moved += moved_round
            if moved_round == 0:
                break
        score = (int((q < LIMIT).sum()), -float(q.min()))
        if score < best[0]:
            best = (score, nodes.copy(), tets, labels, q.copy())
            stale = 0
        else:
            stale += 1
            if stale >= _PATIENCE:
                break
        if cycle == flip_cycles or not (q < target).any():
            break
        tets, labels, q, f23, f32 = _flip_pass(nodes, tets, labels, q, target)
        n23, n32 = n23 + f23, n32 + f32
        nodes, tets, labels, q, ni = _insert_pass(nodes, tets, labels, q, target)
        n_insert += ni
        if f23 + f32 + ni == 0:
            nodes, tets, labels, q, ns = _split_pass(nodes, tets, labels, q, target)
            n_split += ns
            if ns == 0:
                break
        n = len(nodes)
    _, nodes, tets, labels, _ = best
    q = tet_quality(nodes, tets)
    cls = classify_nodes(tets, labels, len(nodes))
    stats = {
        "below_0.2_before": below_before,
        "scaled_jacobian_below_0.2_before": table2_before[0],
        "condition_above_3_before": table2_before[1],
        "below_0.2_after": int((q < LIMIT).sum()),
        "min_quality_before": round(min_before, 4),
        "min_quality_after": round(float(q.min()), 4),
        "nodes_moved": moved,
        "rounds": rounds,
        "flips_2_3": int(n23),
        "flips_3_2": int(n32),
        "nodes_inserted": int(n_insert),
        "edges_split": int(n_split),
        "fixed_nodes": int((cls == -2).sum()),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    return nodes, tets, labels, stats


def repair_stuck(nodes: np.ndarray, tets: np.ndarray, labels: np.ndarray, project, *,
                 rounds: int = 10, tries: int = 3, rings: int = 3, seed: int = 0,
                 iterations: int = 10, flip_cycles: int = 6, random_candidates: int = 64,
                 patience: int = 4, fixed: np.ndarray | None = None):
    """Mend tets that :func:`improve_mesh` leaves below the Table-2 limit: bisect their longest
    edges, surface edges included, and improve the piece of mesh around them again.

    :func:`improve_mesh` keeps every interface triangle's nodes on it and splits only edges
    inside one tissue. A tet with all four nodes and all six edges on one surface (a
    one-tet-thick channel of CSF between two folds of the brain surface, e.g. at the bottom of
    the interhemispheric fissure, each tet with two faces on the brain surface) has no free node
    and no edge inside its tissue: relocation only slides its nodes along the surface, and a
    point inserted into it or its CSF neighbours makes flatter tets (measured on the MNI152
    head's three such tets: the best point found by a random search gave at most q 0.04 against
    their 0.126), since the channel is narrower than the surface's edges along it. Refining the
    surface there mends it: the longest edge of each such tet is split (:func:`split_edges`; a
    surface edge's midpoint is moved onto the input surface when its tets stay positive there,
    and slides along it afterwards), which shortens the channel's tets along it, and
    :func:`improve_mesh` (random candidates) then shapes them (longest-edge refinement with
    smoothing; Rivara 1997, IJNME 40:3313; Freitag & Ollivier-Gooch 1997, IJNME 40:3979).

    Each round works on the piece of mesh within `rings` node rings of the tets below the limit,
    its border held fixed (``improve_mesh(fixed=...)``), so a round costs a fraction of a second
    on a head mesh. A round bisects, then runs the improvement `tries` times (other random
    seeds) and keeps the best try; the next round starts from it. Splitting a poor tet's edge
    halves every tet around it, so the count below the limit may rise on the way; the best
    state over all rounds and the input (fewest tets below the limit, then the best worst
    quality) is returned, so the repair never leaves a worse mesh. It stops when no tet is below
    the limit, after `rounds` rounds, or after `patience` rounds without a better best state.
    Labels never change; split surface triangles are halved in place and their new nodes lie
    on the input surfaces, so each tissue's region changes only as much as a node sliding along
    its surface changes it.

    Arguments:
        nodes: (n, 3) mm; tets: (m, 4) positively oriented; labels: (m,) tissue 1..4.
        project: four callables (BRAIN, CSF, SKULL, SCALP surfaces), as for :func:`improve_mesh`.
        rounds, tries, patience: see above.
        rings: node rings around the poor tets that each round may change.
        seed, iterations, flip_cycles, random_candidates: for :func:`improve_mesh` (its seed is
            seed + tries * round + try).
        fixed: (n,) bool, nodes that never move (and whose edges are split only towards a free
            end), or None: e.g. the border of a piece cut out of a larger mesh.

    Returns:
        (nodes, tets, labels, stats): stats has below_0.2_before/after, min_quality_before/after,
        rounds, edges_bisected and surface_edges_bisected (those on an interface or the
        boundary; both in the returned mesh), nodes_added, seconds. With no tet below the limit
        the input comes back unchanged.
    """
    t0 = time.perf_counter()
    nodes = np.asarray(nodes, dtype=np.float64)
    tets, labels = np.asarray(tets), np.asarray(labels)
    n_in = len(nodes)
    if fixed is not None:
        fixed = np.asarray(fixed, dtype=bool)
        if fixed.shape != (n_in,):
            raise ValueError(f"`fixed` must be a bool mask of the {n_in} nodes, got shape {fixed.shape}.")
    q = tet_quality(nodes, tets)
    score = (int((q < LIMIT).sum()), -float(q.min()))
    stats = {"below_0.2_before": score[0], "min_quality_before": round(-score[1], 4), "rounds": 0}
    cur = best = (score, nodes, tets, labels, q, 0, 0)
    stale = 0
    for r in range(rounds):
        _, nodes, tets, labels, q, n_bis, n_surf = cur
        bad = np.nonzero(q < LIMIT)[0]
        if not len(bad):
            break
        ptr, inc_t, _ = _incidence(tets, len(nodes))
        free = np.zeros(len(nodes), dtype=bool)
        free[tets[bad]] = True
        for _ in range(rings):
            idx = np.nonzero(free)[0]
            free[tets[inc_t[_ranges(ptr[idx], ptr[idx + 1])]]] = True
        idx = np.nonzero(free)[0]
        piece = np.unique(inc_t[_ranges(ptr[idx], ptr[idx + 1])])
        sub = np.unique(tets[piece])  # the piece's nodes: `free` ones and its fixed border
        local = np.full(len(nodes), -1)
        local[sub] = np.arange(len(sub))
        s_fixed = ~free[sub]
        if fixed is not None:
            s_fixed |= (sub < n_in) & fixed[np.minimum(sub, n_in - 1)]  # added nodes are free
        s_nodes, s_tets, s_labels, _, nb, ns = _bisect_pass(
            nodes[sub], local[tets[piece]], labels[piece], q[piece], s_fixed, project)
        if nb == 0:
            break
        stats["rounds"] += 1
        s_fixed = np.concatenate([s_fixed, np.zeros(len(s_nodes) - len(sub), dtype=bool)])
        keep = np.ones(len(tets), dtype=bool)
        keep[piece] = False
        q_rest = q[keep]
        outcome = None
        for k in range(tries):
            o = improve_mesh(s_nodes, s_tets, s_labels, project, iterations=iterations,
                             seed=seed + tries * r + k, flip_cycles=flip_cycles,
                             random_candidates=random_candidates, fixed=s_fixed)
            q_piece = tet_quality(o[0], o[1])
            sc = (int((q_rest < LIMIT).sum() + (q_piece < LIMIT).sum()),
                  -float(min(q_rest.min(initial=np.inf), q_piece.min())))
            if outcome is None or sc < outcome[0]:
                outcome = (sc, o, q_piece)
        sc, (p_nodes, p_tets, p_labels, _), q_piece = outcome
        # Back into the whole mesh: the border nodes did not move, so the piece still fits.
        to_global = np.concatenate([sub, len(nodes) + np.arange(len(p_nodes) - len(sub))])
        nodes = np.concatenate([nodes, p_nodes[len(sub):]])
        nodes[sub] = p_nodes[:len(sub)]
        cur = (sc, nodes, np.concatenate([tets[keep], to_global[p_tets]]),
               np.concatenate([labels[keep], p_labels]), np.concatenate([q_rest, q_piece]),
               n_bis + nb, n_surf + ns)
        if sc < best[0]:
            best, stale = cur, 0
        else:
            stale += 1
            if stale >= patience:
                break
    (below, neg_min), nodes, tets, labels, _, n_bis, n_surf = best
    stats.update({"below_0.2_after": below, "min_quality_after": round(-neg_min, 4),
                  "edges_bisected": n_bis, "surface_edges_bisected": n_surf,
                  "nodes_added": len(nodes) - n_in, "seconds": round(time.perf_counter() - t0, 2)})
    return nodes, tets, labels, stats
