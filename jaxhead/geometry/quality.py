"""Tetrahedron quality as CUBIT/Verdict define it, and the seed paper's Table-2 report.  [jax]

Per-element metrics of linear tets in pure JAX: jit-compiled and differentiable with respect to
node positions (a later study optimises nodes). Definitions follow the Verdict library, which
CUBIT and VTK's vtkMeshQuality both use: Stimpson, Ernst, Knupp, Pebay, Thompson (2007), *The
Verdict Library Reference Manual*, Sandia National Laboratories, section "Tetrahedral metrics".

Nodes P0..P3 of a tet; edges L0 = P1-P0, L1 = P2-P1, L2 = P0-P2, L3 = P3-P0, L4 = P3-P1,
L5 = P3-P2 (Verdict's numbering).

- ``jacobian``: J = (L2 x L0) . L3 = 6 x signed volume (mm^3). Positive for the orientation
  TetMesh uses ((P1-P0) x (P2-P0) . (P3-P0) > 0), which is also VTK's (``vtkTetra``).
- ``scaled_jacobian``: sqrt(2) J / max over the four corners of the product of the three edge
  lengths at that corner (the max is at least |J|, as in Verdict). 1 regular, <= 0 inverted.
- ``distortion``: min over integration points of det(dx/dxi) x master volume / element volume
  (CUBIT's definition). The 4-point Gauss rule on the master tet (volume 1/6) is used; for a
  linear tet the Jacobian is constant, so this is J / |J|: 1 for every positive tet and -1 for
  every inverted one. The element volume is taken as an unsigned size so that inverted tets
  are negative; Verdict's own ``tet_distortion`` returns 1 for every linear tet, inverted or
  not, so only positive tets agree with VTK.
- ``condition``: ||S||_F ||S^-1||_F / 3 with S = A W^-1, A = [L0, -L2, L3] and W the regular
  tet [[1, 1/2, 1/2], [0, sqrt(3)/2, sqrt(3)/6], [0, 0, sqrt(2/3)]]; computed as
  sqrt(||S||_F^2 ||adj S||_F^2) / (3 det S) like Verdict, so it is negative for inverted tets.
- ``radius_ratio``: circumradius / (3 inradius), via Verdict's formula
  |L3|^2 (L2 x L0) + |L2|^2 (L3 x L0) + |L0|^2 (L3 x L2) times the surface area over 108 V^2;
  1 regular, orientation independent.
- ``min_dihedral``: smallest of the six (non-oriented) dihedral angles in degrees; arccos(1/3)
  = 70.53 deg regular, orientation and relabelling independent. VTK's ``min_angle`` (Verdict
  ``tet_minimum_angle``, VTK 9.7) differs on some tets: it pairs like-oriented face normals at
  edges P0P2 and P1P3 and so takes 180 deg minus the dihedral there (checked in the tests), so
  it changes when the nodes are relabelled; ours is the geometric minimum.
- ``volume``: signed volume J / 6 in mm^3.

Degenerate tets (J == 0 exactly): ``condition`` and ``radius_ratio`` are +inf (Verdict returns
its VERDICT_DBL_MAX, 1e30), ``scaled_jacobian``, ``distortion`` and ``min_dihedral`` are 0 (a
flat tet has a zero dihedral angle); a tet collapsed to a point scores 0 scaled Jacobian where
Verdict returns 1e30. Every division and square root is guarded ("double where"), so values are
never NaN for finite input and gradients at degenerate tets are finite (zero through the guarded
branch) instead of NaN.
"""

import math
import os
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._files import atomic_write_path
from .._types import Array, Nodes, Tets
from ..tissue import TISSUES
from .tetmesh import TetMesh

#: Metric names, in the order `tet_metrics` and `metrics` return them.
METRIC_NAMES: tuple[str, ...] = (
    "jacobian",
    "scaled_jacobian",
    "distortion",
    "condition",
    "radius_ratio",
    "min_dihedral",
    "volume",
)

#: Acceptable range of each metric (inclusive bounds, except the strict J > 0 and volume > 0).
#: jacobian, scaled_jacobian, distortion, condition: the seed paper's Table 2 (Vonach et al. 2012,
#: after CUBIT's recommended ranges). radius_ratio and min_dihedral: Verdict reference manual
#: (Stimpson et al. 2007, tet table), also `pyvista.cell_quality_info("TETRA", ...)`.
ACCEPTABLE_RANGES: dict[str, tuple[float, float]] = {
    "jacobian": (0.0, math.inf),
    "scaled_jacobian": (0.2, 1.0),
    "distortion": (0.6, 1.0),
    "condition": (1.0, 3.0),
    "radius_ratio": (1.0, 3.0),
    "min_dihedral": (40.0, math.degrees(math.acos(1.0 / 3.0))),
    "volume": (0.0, math.inf),
}
#: Metrics whose lower bound is strict (an element with exactly 0 is unacceptable).
_STRICT_LOWER = frozenset({"jacobian", "volume"})
#: The seed paper's Table 2 columns: numbers of elements outside these metrics' ranges.
TABLE2_METRICS: tuple[str, ...] = ("jacobian", "scaled_jacobian", "distortion", "condition")

_UNITS = {"jacobian": "mm^3", "volume": "mm^3", "min_dihedral": "deg"}

_SQRT2 = math.sqrt(2.0)
_SQRT3 = math.sqrt(3.0)
_SQRT6 = math.sqrt(6.0)

# 4-point Gauss rule on the master tet {r, s, t >= 0, r + s + t <= 1} (volume 1/6), exact for
# quadratics: a = (5 + 3 sqrt 5) / 20, b = (5 - sqrt 5) / 20, weights 1/24 (the standard
# degree-2 rule, e.g. Keast 1986, CMAME 55:339; Verdict uses 4 points for tets as well).
_GA = (5.0 + 3.0 * math.sqrt(5.0)) / 20.0
_GB = (5.0 - math.sqrt(5.0)) / 20.0
_GAUSS_RST = np.array([[_GB, _GB, _GB], [_GA, _GB, _GB], [_GB, _GA, _GB], [_GB, _GB, _GA]])
_GAUSS_W = np.full(4, 1.0 / 24.0)
_MASTER_VOLUME = 1.0 / 6.0


# --------------------------------------------------------------------------------------------
# Vector algebra. Vectors are tuples of three (n_tets,) arrays (structure of arrays): every
# operation is elementwise, which keeps the XLA program small and fused (measured 2.6x faster
# than (n_tets, 3) arrays with jnp.cross on 335k tets, and 2.4x faster to compile).


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _lin(*terms):
    """sum of c * v over (c, v) pairs with Python-float c."""
    return tuple(sum(c * v[i] for c, v in terms) for i in range(3))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


# Guarded elementary operations: finite values and finite gradients at degenerate input.


def _safe_sqrt(x):
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _norm(v):
    return _safe_sqrt(_dot(v, v))


def _safe_div(num, den, fill):
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fill)


def _safe_atan2(y, x):
    ok = (x != 0) | (y != 0)
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)


def _min(xs):
    out = xs[0]
    for x in xs[1:]:
        out = jnp.minimum(out, x)
    return out


def _max(xs):
    out = xs[0]
    for x in xs[1:]:
        out = jnp.maximum(out, x)
    return out


# --------------------------------------------------------------------------------------------
# The metrics of a batch of tets given their corner coordinates.


def _linear_shape_gradients(rst):
    """dN_a/d(r, s, t) of the linear tet's shape functions at points rst (g, 3): (g, 4, 3)."""
    d = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    return np.broadcast_to(d, (rst.shape[0], 4, 3))  # constant for P1 elements


def _distortion(pts):
    """CUBIT distortion: min_g det(dx/dxi)(g) x master volume / |element volume|."""
    dn = _linear_shape_gradients(_GAUSS_RST)
    dets = []
    for g in range(len(_GAUSS_RST)):
        # column j of dx/dxi at Gauss point g: sum_a x_a dN_a/dxi_j (zero terms skipped)
        cols = [_lin(*[(float(dn[g, a, j]), pts[a]) for a in range(4) if dn[g, a, j] != 0])
                for j in range(3)]
        dets.append(_dot(cols[0], _cross(cols[1], cols[2])))
    elem_volume = sum(float(w) * d for w, d in zip(_GAUSS_W, dets))
    return _safe_div(_min(dets) * _MASTER_VOLUME, jnp.abs(elem_volume), 0.0)


def _metrics_of_corners(pts):
    """All metrics of tets with corners pts[a] = (x, y, z) arrays (n_tets,), in mm."""
    p0, p1, p2, p3 = pts
    l0, l1, l2 = _sub(p1, p0), _sub(p2, p1), _sub(p0, p2)
    l3, l4, l5 = _sub(p3, p0), _sub(p3, p1), _sub(p3, p2)
    sq = [_dot(v, v) for v in (l0, l1, l2, l3, l4, l5)]
    l2xl0, l3xl0, l3xl2, l4xl1 = _cross(l2, l0), _cross(l3, l0), _cross(l3, l2), _cross(l4, l1)
    jac = _dot(l2xl0, l3)
    abs_jac = jnp.abs(jac)

    # Scaled Jacobian (Verdict tet_scaled_jacobian).
    corner = [sq[0] * sq[2] * sq[3], sq[0] * sq[1] * sq[4],
              sq[1] * sq[2] * sq[5], sq[3] * sq[4] * sq[5]]
    length_product = jnp.maximum(_safe_sqrt(_max(corner)), abs_jac)
    scaled_jacobian = _SQRT2 * _safe_div(jac, length_product, 0.0)

    # Condition number with the regular tet as the target (Verdict tet_condition): the columns
    # of S = A W^-1 are c1..c3.
    c1 = l0
    c2 = _lin((-2.0 / _SQRT3, l2), (-1.0 / _SQRT3, l0))
    c3 = _lin((3.0 / _SQRT6, l3), (1.0 / _SQRT6, l2), (-1.0 / _SQRT6, l0))
    frob2 = _dot(c1, c1) + _dot(c2, c2) + _dot(c3, c3)
    c12, c23, c13 = _cross(c1, c2), _cross(c2, c3), _cross(c1, c3)
    adj2 = _dot(c12, c12) + _dot(c23, c23) + _dot(c13, c13)
    det_s = _dot(c1, c23)
    condition = _safe_div(_safe_sqrt(frob2 * adj2), 3.0 * det_s, jnp.inf)

    # Radius ratio (Verdict tet_radius_ratio): |circumcentre numerator| x area / (108 V^2).
    volume = jac / 6.0
    numerator = tuple(sq[3] * a + sq[2] * b + sq[0] * c for a, b, c in zip(l2xl0, l3xl0, l3xl2))
    area = 0.5 * (_norm(l2xl0) + _norm(l3xl0) + _norm(l4xl1) + _norm(l3xl2))
    radius_ratio = _safe_div(_norm(numerator) * area, 108.0 * volume * volume, jnp.inf)

    # Dihedral angles. The four cross products above are the faces' area vectors (twice the
    # area), all pointing into the tet when J > 0 and all out of it when J < 0: face opposite P3
    # l2xl0, P2 l3xl0, P1 l3xl2, P0 l4xl1. Faces opposite Pi and Pj share edge PkPl and, for
    # n = area vectors, |ni x nj| = |J| |PkPl| and ni . nj = -|ni||nj| cos(dihedral); atan2 of
    # the two is accurate near 0 and 180 deg, unlike acos, and independent of orientation.
    face = {3: l2xl0, 2: l3xl0, 1: l3xl2, 0: l4xl1}
    edges = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))  # L0..L5
    edge_sq = dict(zip(edges, sq))
    angles = []
    for (k, l), e2 in edge_sq.items():
        i, j = (n for n in range(4) if n not in (k, l))
        angles.append(_safe_atan2(_safe_sqrt(e2) * abs_jac, -_dot(face[i], face[j])))
    min_dihedral = jnp.rad2deg(_min(angles))

    return {
        "jacobian": jac,
        "scaled_jacobian": scaled_jacobian,
        "distortion": _distortion(pts),
        "condition": condition,
        "radius_ratio": radius_ratio,
        "min_dihedral": min_dihedral,
        "volume": volume,
    }


def _corners(nodes, tets):
    """Corner coordinates as 4 tuples of (x, y, z) arrays of shape (n_tets,)."""
    comp = [nodes[:, c][tets] for c in range(3)]  # (n_tets, 4) each
    return [tuple(comp[c][:, a] for c in range(3)) for a in range(4)]


@jax.jit
def _tet_metrics_jit(nodes, tets):
    return _metrics_of_corners(_corners(nodes, tets))


def _check_nodes_tets(nodes, tets):
    """Validate shapes/dtypes at the API boundary; returns (nodes, tets) as jax arrays."""
    nodes = jnp.asarray(nodes)
    tets = jnp.asarray(tets)
    if nodes.ndim != 2 or nodes.shape[1] != 3:
        raise ValueError(f"`nodes` must have shape (n_nodes, 3) in mm, got {nodes.shape}.")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"`tets` must have shape (n_tets, 4), got {tets.shape}.")
    if not jnp.issubdtype(tets.dtype, jnp.integer):
        raise ValueError(f"`tets` must hold integer node indices, got dtype {tets.dtype}.")
    if not jnp.issubdtype(nodes.dtype, jnp.floating):
        nodes = nodes.astype(jnp.result_type(float))
    try:  # concrete indices: check the range here with a clear message
        t = np.asarray(tets)
    except jax.errors.TracerArrayConversionError:  # under an outer jit: check at run time
        bad = (tets < 0) | (tets >= nodes.shape[0])
        tets = eqx.error_if(tets, bad, "`tets` indexes a node outside 0..n_nodes-1.")
    else:
        if t.size and (t.min() < 0 or t.max() >= nodes.shape[0]):
            raise ValueError(
                f"`tets` indexes nodes {t.min()}..{t.max()} but there are {nodes.shape[0]} "
                "nodes; indices must be 0-based and < n_nodes."
            )
    return nodes, tets


def tet_metrics(nodes: Nodes, tets: Tets) -> dict[str, jax.Array]:
    """Verdict quality metrics of every tet; jit-compiled, differentiable w.r.t. `nodes`.

    Arguments:
        nodes: (n_nodes, 3) node positions in mm (float64 if jax_enable_x64 is on).
        tets: (n_tets, 4) integer node indices (any orientation; inverted tets score negative
            jacobian, scaled_jacobian, distortion, condition and volume).

    Returns:
        dict with keys `METRIC_NAMES` (jacobian [mm^3], scaled_jacobian, distortion, condition,
        radius_ratio, min_dihedral [deg], volume [mm^3]), each a (n_tets,) array of the
        nodes' dtype. See the module docstring for definitions and degenerate-tet values.
    """
    nodes, tets = _check_nodes_tets(nodes, tets)
    out = _tet_metrics_jit(nodes, tets)
    return {k: out[k] for k in METRIC_NAMES}


def metrics(mesh: TetMesh) -> dict[str, np.ndarray]:
    """Verdict quality metrics of every tet of a TetMesh, as NumPy arrays.

    Arguments:
        mesh: the TetMesh (nodes in mm).

    Returns:
        dict with exactly the keys jacobian, scaled_jacobian, distortion, condition,
        radius_ratio, min_dihedral, volume; each (n_tets,) float (float64 with
        jax_enable_x64 on; JAX's default float32 otherwise).
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(
            f"`mesh` must be a jaxhead TetMesh, got {type(mesh).__name__}; for raw arrays "
            "use `tet_metrics(nodes, tets)`."
        )
    out = tet_metrics(mesh.nodes, mesh.tets)
    return {k: np.asarray(out[k]) for k in METRIC_NAMES}


def shape_objective(nodes: Nodes, tets: Tets, *, delta: float = 0.0) -> jax.Array:
    """Smooth per-tet shape distortion eta = ||S||_F^2 / (3 h(det S)^(2/3)) for node optimisation.

    eta is Knupp's inverse mean ratio with the regular tet as target (1 for a regular tet,
    > 1 otherwise; 1 / Verdict's ``shape``), scale invariant and smooth where det S > 0. With
    delta > 0, det S = sigma is replaced by h(sigma) = (sigma + sqrt(sigma^2 + 4 delta^2)) / 2,
    which is positive for every sigma, so the summed objective is finite and smooth for
    tangled meshes too (Escobar, Rodriguez, Montenegro, Montero, Gonzalez-Yuste 2003,
    Simultaneous untangling and smoothing of tetrahedral meshes, CMAME 192:2775).

    Arguments:
        nodes: (n_nodes, 3) node positions in mm.
        tets: (n_tets, 4) node indices.
        delta: regularisation of det S in mm^3 (0: exact eta, +inf for inverted/flat tets).

    Returns:
        (n_tets,) eta; sum or mean it for a mesh objective.
    """
    if isinstance(delta, (int, float)) and not delta >= 0.0:  # traced values: caller's duty
        raise ValueError(f"`delta` must be >= 0 (mm^3), got {delta}.")
    nodes, tets = _check_nodes_tets(nodes, tets)
    return _shape_objective_jit(nodes, tets, delta)


@jax.jit
def _shape_objective_jit(nodes, tets, delta):
    p0, p1, p2, p3 = _corners(nodes, tets)
    l0, l2, l3 = _sub(p1, p0), _sub(p0, p2), _sub(p3, p0)
    c1 = l0
    c2 = _lin((-2.0 / _SQRT3, l2), (-1.0 / _SQRT3, l0))
    c3 = _lin((3.0 / _SQRT6, l3), (1.0 / _SQRT6, l2), (-1.0 / _SQRT6, l0))
    frob2 = _dot(c1, c1) + _dot(c2, c2) + _dot(c3, c3)
    sigma = _dot(c1, _cross(c2, c3))
    h = 0.5 * (sigma + _safe_sqrt(sigma * sigma + 4.0 * delta * delta))
    ok = h > 0  # h == 0 only for delta == 0 and sigma <= 0: inverted or flat, eta = +inf
    return jnp.where(ok, frob2 / (3.0 * jnp.where(ok, h, 1.0) ** (2.0 / 3.0)), jnp.inf)


# --------------------------------------------------------------------------------------------
# The Table-2 report.


def outside_range(name: str, values: Array) -> np.ndarray:
    """Boolean mask of elements outside `ACCEPTABLE_RANGES[name]` (NaN counts as outside).

    Arguments:
        name: a metric name from `METRIC_NAMES`.
        values: (n_tets,) metric values.

    Returns:
        (n_tets,) bool.
    """
    if name not in ACCEPTABLE_RANGES:
        raise ValueError(f"`name` {name!r} is not a metric; use one of {list(METRIC_NAMES)}.")
    x = np.asarray(values)
    lo, hi = ACCEPTABLE_RANGES[name]
    if name in _STRICT_LOWER:
        return ~(x > lo)
    # Bounds that the ideal element attains (condition 1, scaled Jacobian 1, 70.53 deg) come out
    # a few ulps off in floating point; 64 ulps (1.4e-14 in float64) of slack keeps a perfect
    # element inside without moving any real count.
    tol = 64.0 * np.finfo(x.dtype if np.issubdtype(x.dtype, np.floating) else np.float64).eps
    return ~((x >= lo - tol * max(1.0, abs(lo))) & (x <= hi + tol * max(1.0, abs(hi))))


_PERCENTILES = (1.0, 5.0, 50.0, 95.0, 99.0)


def _stats(x: np.ndarray) -> dict[str, float]:
    q = np.percentile(x, _PERCENTILES)
    out = {"min": float(x.min()), "mean": float(x.mean()), "max": float(x.max())}
    out.update({f"p{int(p)}": float(v) for p, v in zip(_PERCENTILES, q)})
    return out


@dataclass(frozen=True)
class QualityReport:
    """The seed paper's Table-2 row plus per-tissue statistics of the Verdict metrics.

    Arguments:
        n_tets: number of elements.
        outside: metric -> number of elements outside `ranges[metric]` (whole mesh).
        ranges: metric -> (low, high) acceptable range used.
        stats: metric -> {"min", "p1", "p5", "p50", "mean", "p95", "p99", "max"} over the mesh.
        tissues: tissue name -> {"n_tets": int, "outside": {metric: int},
            "stats": {metric: {...}}}, for the tissues present in the mesh.
        png_paths: histogram files written (empty if none).
    """

    n_tets: int
    outside: dict[str, int]
    ranges: dict[str, tuple[float, float]]
    stats: dict[str, dict[str, float]]
    tissues: dict[str, dict] = field(default_factory=dict)
    png_paths: tuple[str, ...] = ()

    @property
    def table2_row(self) -> dict[str, int]:
        """The paper's Table 2 row: element count and elements outside each range."""
        row = {"elements": self.n_tets}
        row.update({m: self.outside[m] for m in TABLE2_METRICS})
        return row

    def table(self) -> str:
        """A readable plain-text table of the report."""
        lines = [
            f"Tetrahedral mesh quality (Verdict/CUBIT definitions): {self.n_tets} elements", ""
        ]
        lines.append("Elements outside the acceptable ranges (seed paper Table 2):")
        heads = ["elements", "Jacobian <= 0"] + [
            f"{m.replace('_', ' ')} not in [{self.ranges[m][0]:g}, {self.ranges[m][1]:g}]"
            for m in TABLE2_METRICS[1:]
        ]
        vals = [str(v) for v in self.table2_row.values()]
        widths = [max(len(h), len(v)) for h, v in zip(heads, vals)]
        lines.append("  " + "  ".join(h.rjust(w) for h, w in zip(heads, widths)))
        lines.append("  " + "  ".join(v.rjust(w) for v, w in zip(vals, widths)))
        lines.append("")
        lines.append("Statistics per tissue ('outside' counts elements outside the range):")
        cols = ["tissue", "n_tets", "metric", "unit", "min", "p1", "p50", "mean", "p99", "max",
                "range", "outside"]
        rows = []
        groups = [("all", self.n_tets, self.stats, self.outside)] + [
            (name, t["n_tets"], t["stats"], t["outside"]) for name, t in self.tissues.items()
        ]
        for name, n, stats, outside in groups:
            for m in METRIC_NAMES:
                s = stats[m]
                lo, hi = self.ranges[m]
                rows.append([name, str(n), m, _UNITS.get(m, "-")]
                            + [f"{s[k]:.4g}" for k in ("min", "p1", "p50", "mean", "p99", "max")]
                            + [f"[{lo:.4g}, {hi:.4g}]", str(outside[m])])
        widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
        lines.append("  ".join(c.ljust(w) for c, w in zip(cols, widths)).rstrip())
        for r in rows:
            lines.append("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
        if self.png_paths:
            lines.append("")
            lines.append("Histograms: " + ", ".join(self.png_paths))
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats, e.g. +inf of degenerate tets, become None)."""

        def clean(o):
            if isinstance(o, dict):
                return {str(k): clean(v) for k, v in o.items()}
            if isinstance(o, (list, tuple)):
                return [clean(v) for v in o]
            if isinstance(o, float):
                return o if math.isfinite(o) else None
            return o

        return clean({
            "n_tets": self.n_tets,
            "table2_row": self.table2_row,
            "outside": self.outside,
            "ranges": {k: list(v) for k, v in self.ranges.items()},
            "stats": self.stats,
            "tissues": self.tissues,
            "png_paths": list(self.png_paths),
        })


def quality_report(mesh: TetMesh, *, png_dir: str | os.PathLike | None = None) -> QualityReport:
    """Quality report of a mesh: the seed paper's Table-2 row and per-tissue statistics.

    Arguments:
        mesh: the TetMesh.
        png_dir: if given, write one histogram per metric there (``quality_<metric>.png``,
            stacked by tissue, acceptable range shaded); the folder is created if missing.

    Returns:
        QualityReport (counts use `ACCEPTABLE_RANGES`; Table 2 uses jacobian, scaled_jacobian,
        distortion and condition).
    """
    q = metrics(mesh)
    labels = np.asarray(mesh.labels)
    outside = {m: int(outside_range(m, q[m]).sum()) for m in METRIC_NAMES}
    stats = {m: _stats(q[m]) for m in METRIC_NAMES}
    tissues = {}
    for t in TISSUES:
        sel = labels == int(t)
        if not sel.any():
            continue
        tissues[t.name.lower()] = {
            "n_tets": int(sel.sum()),
            "outside": {m: int(outside_range(m, q[m][sel]).sum()) for m in METRIC_NAMES},
            "stats": {m: _stats(q[m][sel]) for m in METRIC_NAMES},
        }
    paths = () if png_dir is None else _write_histograms(q, labels, os.fspath(png_dir))
    return QualityReport(
        n_tets=int(mesh.n_tets),
        outside=outside,
        ranges=dict(ACCEPTABLE_RANGES),
        stats=stats,
        tissues=tissues,
        png_paths=paths,
    )


def _write_histograms(
    q: dict[str, np.ndarray], labels: np.ndarray, png_dir: str
) -> tuple[str, ...]:
    """One PNG per metric: histogram stacked by tissue, log counts, acceptable range shaded."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    os.makedirs(png_dir, exist_ok=True)
    present = [t for t in TISSUES if np.any(labels == int(t))]
    paths = []
    for m in METRIC_NAMES:
        x = q[m]
        finite = np.isfinite(x)
        xf = x[finite]
        lo, hi = ACCEPTABLE_RANGES[m]
        fig = Figure(figsize=(6.4, 4.0))
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        if xf.size:
            x0, x1 = float(xf.min()), float(xf.max())
            # Long positive tails (condition, radius ratio, volumes) read better on log bins.
            logx = x0 > 0 and x1 / x0 > 100.0
            if x1 == x0:
                x0, x1 = x0 - 0.5 * max(abs(x0), 1e-12), x1 + 0.5 * max(abs(x1), 1e-12)
            bins = np.geomspace(x0, x1, 61) if logx else np.linspace(x0, x1, 61)
            data = [x[finite & (labels == int(t))] for t in present]
            # stepfilled: one polygon per tissue, far cheaper to render than 60 bars each
            ax.hist(data, bins=bins, stacked=True, histtype="stepfilled", log=True,
                    label=[t.name.lower() for t in present])
            if logx:
                ax.set_xscale("log")
            left, right = ax.get_xlim()
            if max(lo, left) < min(hi, right):
                ax.axvspan(max(lo, left), min(hi, right), color="tab:green", alpha=0.15,
                           label=f"acceptable [{lo:.3g}, {hi:.3g}]")
            ax.set_xlim(left, right)
            n_bad = int(outside_range(m, x).sum())
            title = f"{m} ({n_bad} of {x.size} outside)"
        else:
            title = f"{m} (no finite values)"
        if (~finite).any():
            title += f", {int((~finite).sum())} non-finite not shown"
        ax.set_title(title)
        ax.set_xlabel(f"{m} [{_UNITS[m]}]" if m in _UNITS else m)
        ax.set_ylabel("elements")
        ax.legend(fontsize="small")
        fig.tight_layout()
        path = os.path.join(png_dir, f"quality_{m}.png")
        with atomic_write_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
        paths.append(path)
    return tuple(paths)
