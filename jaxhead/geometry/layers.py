"""Segmentation post-processing into four strictly nested layers (Vonach et al. 2012, sec. 2.3).  [host]

The seed paper cleans the argmax label map by hand-tuned steps before meshing: 2D morphological
closing of each layer, a skull mask ``skull U brain U dilate_3x3x3(CSF)`` so a thin skull surrounds
the CSF everywhere, and the brain eroded by 2x2x2 where the CSF is too thin. :func:`make_layers`
does the same as explicit 3D rules, in this order, and counts every relabelled voxel:

0. ``fov``: a head cut by the volume border (a field of view ending at the neck, the vertex or
   the face) is closed (``fov_cut="close"``, the default): the grid is padded beyond every cut
   face, and each shell is capped there, inside out, by the voxels of the pad within its minimum
   thickness of the inner solid (CSF over a cut brain, skull over CSF, scalp over skull), so
   nesting and thickness hold across the cut. The cut faces, their tissue and what was added are
   in :class:`LayerReport` (``fov_cuts``); the output grid is the input grid grown by the pad on
   the cut sides. ``fov_cut="error"`` refuses such a map.
1. ``closing``: per-layer morphological closing (3D ball of ``closing_radius_mm``, voxel-size
   aware) of each tissue mask of the input; where two closings claim a voxel the outer layer wins
   (BRAIN < CSF < SKULL < SCALP), so a CSF channel through the skull is sealed by skull (skull
   pinholes shunt current: they matter most for EIT). The brain is not closed by default: its
   closing fills the sulci up to two radii wide with brain, i.e. removes the sulcal CSF (on the
   ANTs head at 2 mm 6164 voxels, 49 cm^3, a fifth of its CSF), and the brain is no shell
   whose pinholes shunt current; its tunnels are rule ``tunnels``' work, which plugs each with
   one cross-section of its channel. Where that rule leaves the brain a handle, the rules run
   again with the brain closed too (default radii only; ``LayerReport.brain_closed``, a warning).
2. ``ventricles``: CSF enclosed by brain (a cavity of the brain solid) becomes BRAIN
   (``ventricles="brain"``, the default: the nested-surface mesh has one brain solid) or is kept
   (``ventricles="keep"``: counted, and treated as part of the brain solid by later rules).
3. ``holes``: every cavity of each nested solid S_k = {1 <= label <= k} (BRAIN; +CSF; +SKULL;
   head) takes label k, inside out.
4. ``components``: each nested solid keeps only its largest face-connected component, outside in;
   dropped voxels take the label of the next solid out (background for the head).
4a. ``thin``: the skull and head solids lose their parts thinner than two voxels across (an
   opening by a 2x2x2 block: a voxel stays when some 2x2x2 block of the solid holds it), outside
   in, where they are the shell's own tissue outside the inner solid's nesting and thickness
   band; those voxels take the next tissue out (``thin="remove"``, the default; ``"keep"``
   leaves them). A one-voxel rod or sheet of bone (the mandible and zygoma of a 2 mm
   segmentation) presmoothed and remeshed is a tube or sheet thinner than a millimetre, all of
   whose tet nodes lie on one surface: the tets across it cannot be shaped by moving nodes along
   the surface (the ANTs head at 2 mm kept 2-4 tets outside Table 2 there). On the ANTs head at
   2 mm this moves 2302 skull voxels (3.6 % of its skull, with the pieces it disconnects) to
   scalp. The brain and CSF solids are left as they are (the CSF is what EIT is most sensitive
   to).
4b. ``tunnels``: each nested solid is made a topological ball (genus 0), outside in: a tunnel
   through a solid (a channel of outer tissue through the skull, a bridge of scalp over a
   groove) is a handle of its surface, which remeshing at edges wider than the tunnel collapses
   into a self-intersecting knot. Tunnels are plugged with the smallest closing that removes
   them: the voxels a closing of radius 1, 2, ... ``max_tunnel_voxels`` voxels adds to the solid
   are split into connected pieces, and only pieces that raise the solid's Euler characteristic
   (a plug, not a groove filler) are added, as the solid's own shell tissue. For the brain solid
   only one cross-section of the piece is added, three voxels thick (:func:`_thin_plug`): its
   complement is sulcal CSF, a network of channels one closing piece joins (on the ANTs head at
   2 mm 11 whole pieces filled 5144 CSF voxels, 41 cm^3, and plugged its 32 handles); the shells'
   plugs stay whole (a sealed channel through a shell is what matters for current flow). A handle no such
   closing plugs is a bar of the solid over a wide opening (in a real skull, thin bony bars of
   the face and skull base: five in the ANTs head at 2 mm, by the zygoma and the mandible): it is cut
   instead, by the dual rule, openings of the same radii, thinned to one cross-section of the
   bar (widened to the opening's diameter) and relabelled as the next tissue out (``handles_cut`` in the report). The rule runs again
   after rule 6 (whose growth can bridge a groove), followed by rules 5 and 6; the genus of each
   solid before and after is in the report. A handle left after that (both the bar and the
   opening wider than ``2 max_tunnel_voxels`` voxels, e.g. a tunnel under a fragmented scalp) is
   wide against the surface edges, so its surface resolves it; it is kept, reported in
   ``genus_after`` and logged as a warning.
5. ``nesting``: strict nesting for every shell: no voxel of S_k has a face neighbour
   (``nesting="face"``, the default) or any of its 26 neighbours (``nesting="cube"``, the
   paper's 3x3x3 rule) outside S_(k+1). The CSF shell takes brain voxels (the paper's brain
   erosion); the skull and scalp shells grow outward (the paper's skull = skull U brain U
   dilate(CSF)). With face nesting no grid edge joins S_k to the outside of S_(k+1), so the
   level-0.5 marching-cubes surfaces of consecutive solids share no vertex, and the surface
   stage's gap step separates them to ``min_gap_mm``; the cube rule keeps them in disjoint
   cubes, but turns every brain voxel diagonal to the skull into CSF: on the demo's MRI
   segmentation (2 mm) it adds 69 cm^3 of CSF (28 % of the 244 cm^3 segmented), the face rule
   34 cm^3, and the CSF shunt is what EIT is most sensitive to.
6. ``thickness``: the same in mm: every voxel whose centre lies within ``min_thickness_mm[T]`` of
   the inner solid belongs to shell T (so the shell is at least that thick, rounded down to whole
   voxels). CSF takes brain; skull and scalp grow outward. The default is one voxel or
   ``MIN_SHELL_MM`` (2 mm), whichever is larger: a shell must not be much thinner than the
   triangles of the surfaces that bound it (CSF 4 mm, brain 6 mm by default), or the constrained-
   Delaunay meshers, which keep those triangles, fill it with flat tets that no improvement
   mends (interface nodes only slide along their surfaces). One-voxel shells are 2 mm thick at
   2 mm, where every case of the hard-label corpus meshes clean, and 1 mm at 1 mm, where a
   one-voxel CSF over half the brain left 1038 tets below scaled Jacobian 0.2 after 218 s of
   improvement (experiments/results/hard_labels_mesh_1mm.md).

After rules 5 and 6 the solids are made hole-free and connected again (counted under the rule).
All connectivity is face (6-) connectivity for both a solid and its complement, which errs
towards removing diagonal-only contacts and tunnels: both make non-manifold surfaces.
"""

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from scipy import ndimage as ndi

from ..masks import largest_component
from ..tissue import TISSUES, Tissue, per_tissue
from ..volume import LabelMap

log = logging.getLogger(__name__)

#: The rules of :func:`make_layers`, in the order they run.
RULES: tuple[str, ...] = ("fov", "closing", "ventricles", "holes", "components", "thin",
                          "tunnels", "nesting", "thickness")

_CROSS = ndi.generate_binary_structure(3, 1)  # 6-connectivity
_CUBE = np.ones((3, 3, 3), dtype=bool)  # 26-neighbourhood (the paper's 3x3x3)
_BLOCK = np.ones((2, 2, 2), dtype=bool)  # the thinnest solid piece kept by rule ``thin``
_SHELLS = (Tissue.CSF, Tissue.SKULL, Tissue.SCALP)

#: Default minimum shell thickness (mm) where a voxel is thinner: half the CSF surface's default
#: edge (4 mm, ``jaxhead.geometry.surface``), so a tet between the two surfaces of a shell is at
#: worst about half as high as it is wide (rule 6 in the module docstring).
MIN_SHELL_MM = 2.0


@dataclass(frozen=True, kw_only=True)
class LayerConfig:
    """Settings of :func:`make_layers`.

    Arguments:
        closing_radius_mm: ball radius of the per-layer closing, one number or per tissue
            ("brain", "csf", "skull", "scalp"); None = for the shells (CSF, skull, scalp) 2 mm or
            one voxel (the largest voxel edge), whichever is larger, so one-voxel pinholes always
            close, and 0 for the brain (its closing would fill the sulci: the module docstring,
            rule 1). 0 disables the closing. One number applies to all four, brain included.
        min_thickness_mm: minimum shell thickness per shell ("csf", "skull", "scalp"), one number
            or a mapping; None or a missing key = ``MIN_SHELL_MM`` (2 mm) or one voxel (the
            largest voxel edge), whichever is larger (rule 6 in the module docstring: thinner
            shells mesh into flat tets). The nesting rule already gives every shell at least
            one voxel.
        nesting: "face" (default): no voxel of a solid has a face neighbour outside the next
            solid out; "cube": no 26-neighbour (the seed paper's 3x3x3 rule; thicker shells,
            CSF taken from the brain wherever the brain is diagonal to the skull).
        ventricles: "brain" relabels CSF enclosed by brain to BRAIN (the nested-surface mesh has
            one brain solid); "keep" keeps it as CSF (counted in the report).
        fov_cut: "close" caps a head cut by the volume border (neck, vertex, face; any side) and
            pads the grid there (rule ``fov``, reported); "error" raises ValueError instead.
        tunnels: "plug" makes every nested solid genus 0 (rule ``tunnels``: plugs, else cuts,
            up to `max_tunnel_voxels`); "keep" leaves tunnels (their surfaces may then
            self-intersect after remeshing).
        max_tunnel_voxels: largest closing (plug) and opening (cut) radius, in voxels, tried on
            a tunnel.
        thin: "remove": skull and scalp parts thinner than two voxels across (outside the
            nesting and thickness band) become the next tissue out (rule ``thin``); "keep".
    """

    closing_radius_mm: float | dict[str, float] | None = None
    min_thickness_mm: float | dict[str, float] | None = None
    ventricles: Literal["brain", "keep"] = "brain"
    fov_cut: Literal["close", "error"] = "close"
    tunnels: Literal["plug", "keep"] = "plug"
    max_tunnel_voxels: int = 4
    nesting: Literal["face", "cube"] = "face"
    thin: Literal["remove", "keep"] = "remove"

    def __post_init__(self):
        if self.nesting not in ("face", "cube"):
            raise ValueError(f"`nesting` = {self.nesting!r}; choose 'face' (6-neighbours, the "
                             "default) or 'cube' (26-neighbours, the seed paper's 3x3x3 rule).")
        if self.thin not in ("remove", "keep"):
            raise ValueError(f"`thin` = {self.thin!r}; choose 'remove' (skull and scalp parts "
                             "thinner than two voxels become the next tissue out) or 'keep'.")
        if self.fov_cut not in ("close", "error"):
            raise ValueError(f"`fov_cut` = {self.fov_cut!r}; choose 'close' (cap the head at the "
                             "volume border) or 'error'.")
        if self.tunnels not in ("plug", "keep"):
            raise ValueError(f"`tunnels` = {self.tunnels!r}; choose 'plug' or 'keep'.")
        if (isinstance(self.max_tunnel_voxels, bool) or not isinstance(self.max_tunnel_voxels, int)
                or not 1 <= self.max_tunnel_voxels <= 16):
            raise ValueError(f"`max_tunnel_voxels` must be an integer in 1..16, got "
                             f"{self.max_tunnel_voxels!r}.")
        if self.closing_radius_mm is not None:
            per_tissue(self.closing_radius_mm, "closing_radius_mm", positive=False)
        if self.min_thickness_mm is not None:
            per_tissue(self.min_thickness_mm, "min_thickness_mm", allowed=_SHELLS, allow_none=True, positive=False)
        if self.ventricles not in ("brain", "keep"):
            raise ValueError(f"`ventricles` = {self.ventricles!r}; choose 'brain' or 'keep'.")

    def closing_radii(self, voxel_mm) -> dict[Tissue, float]:
        """Closing radius per tissue in mm for this voxel size."""
        if self.closing_radius_mm is None:
            r = max(2.0, float(np.max(voxel_mm)))
            return {t: (0.0 if t == Tissue.BRAIN else r) for t in TISSUES}
        return per_tissue(self.closing_radius_mm, "closing_radius_mm", positive=False)

    def thicknesses(self, voxel_mm) -> dict[Tissue, float]:
        """Minimum thickness per shell (CSF, SKULL, SCALP) in mm for this voxel size."""
        default = max(MIN_SHELL_MM, float(np.max(voxel_mm)))
        given = per_tissue(self.min_thickness_mm, "min_thickness_mm", allowed=_SHELLS, allow_none=True, positive=False)
        return {t: (default if v is None else v) for t, v in given.items()}


@dataclass(frozen=True)
class LayerReport:
    """What :func:`make_layers` changed, rule by rule.

    Arguments:
        shape: the input grid's shape (x, y, z) (the output's is larger by `padding`).
        voxel_mm: voxel edge lengths in mm.
        changes: rule -> {(from Tissue, to Tissue): voxels relabelled}; the net change of the
            rule (label before the rule vs after it), so the numbers add up to real voxels.
        dropped_components: solid (its Tissue) -> number of components removed (all rules).
        ventricle_voxels: CSF voxels enclosed by brain found (relabelled or kept, see `ventricles`).
        ventricles: the option used ("brain" or "keep").
        closing_radius_mm, min_thickness_mm: the effective settings (mm).
        volumes_before_mm3, volumes_after_mm3: tissue volumes before and after (mm^3).
        fov_cuts: one dict per volume face the head was cut by (rule ``fov``): "face" ("z=0"),
            "side" (its anatomical direction from the affine: "inferior" for a neck cut),
            "tissue_voxels" and "tissues" (voxels on that face), "area_mm2", "pad_voxels" and
            "pad_mm" (grid added beyond it).
        padding: voxels added to the grid per side, ((x0, x1), (y0, y1), (z0, z1)); the output
            grid is the input grid grown by it (affine shifted so world positions are kept).
        tunnels_plugged: solid (its Tissue) -> pieces added to plug tunnels.
        handles_cut: solid (its Tissue) -> pieces removed to cut handles no plug could close.
        genus_before, genus_after: solid -> genus (handles) before rule ``tunnels`` and at the end,
            from the Euler characteristic of the voxel solid (closed cubes).
        nesting: the nesting rule used ("face" or "cube", :class:`LayerConfig`).
        thin: the thin-part rule used ("remove" or "keep").
        brain_closed: True when the brain was closed because the tunnel rule left it handles
            (the fallback of :func:`make_layers_reported`: default closing radii only).
    """

    shape: tuple[int, int, int]
    voxel_mm: tuple[float, float, float]
    changes: Mapping[str, Mapping[tuple[Tissue, Tissue], int]]
    dropped_components: Mapping[Tissue, int]
    ventricle_voxels: int
    ventricles: str
    closing_radius_mm: Mapping[Tissue, float]
    min_thickness_mm: Mapping[Tissue, float]
    volumes_before_mm3: Mapping[Tissue, float]
    volumes_after_mm3: Mapping[Tissue, float]
    fov_cuts: tuple = ()
    padding: tuple = ((0, 0), (0, 0), (0, 0))
    tunnels_plugged: Mapping[Tissue, int] = field(default_factory=dict)
    handles_cut: Mapping[Tissue, int] = field(default_factory=dict)
    genus_before: Mapping[Tissue, int] = field(default_factory=dict)
    genus_after: Mapping[Tissue, int] = field(default_factory=dict)
    nesting: str = "face"
    thin: str = "remove"
    brain_closed: bool = False

    def n_changed(self, rule: str | None = None, tissue: Tissue | str | int | None = None) -> int:
        """Voxels relabelled by `rule` (None: all rules), optionally only those to or from `tissue`."""
        if rule is not None and rule not in self.changes:
            raise ValueError(f"unknown rule {rule!r}; rules are {list(self.changes)}.")
        t = None if tissue is None else Tissue.parse(tissue)
        total = 0
        for r in ([rule] if rule else self.changes):
            for (a, b), n in self.changes[r].items():
                if t is None or t in (a, b):
                    total += n
        return total

    def net_change(self, tissue: Tissue | str | int, rule: str | None = None) -> int:
        """Voxels gained minus lost by `tissue` (under `rule`, or all rules)."""
        t = Tissue.parse(tissue)
        net = 0
        for r in ([rule] if rule else self.changes):
            for (a, b), n in self.changes[r].items():
                net += n * ((b == t) - (a == t))
        return net

    def to_dict(self) -> dict:
        """A JSON-serialisable dict (tissue names as keys, 'from->to' strings for changes)."""
        name = lambda t: Tissue(t).name.lower()  # noqa: E731
        return {
            "shape": list(self.shape),
            "voxel_mm": list(self.voxel_mm),
            "total_changed": self.n_changed(),
            "changes": {r: {f"{name(a)}->{name(b)}": int(n) for (a, b), n in c.items()}
                        for r, c in self.changes.items()},
            "dropped_components": {name(t): int(n) for t, n in self.dropped_components.items()},
            "ventricle_voxels": int(self.ventricle_voxels),
            "ventricles": self.ventricles,
            "nesting": self.nesting,
            "thin": self.thin,
            "brain_closed": bool(self.brain_closed),
            "closing_radius_mm": {name(t): v for t, v in self.closing_radius_mm.items()},
            "min_thickness_mm": {name(t): v for t, v in self.min_thickness_mm.items()},
            "volumes_before_mm3": {name(t): v for t, v in self.volumes_before_mm3.items()},
            "volumes_after_mm3": {name(t): v for t, v in self.volumes_after_mm3.items()},
            "fov_cuts": [dict(c) for c in self.fov_cuts],
            "padding": [list(p) for p in self.padding],
            "tunnels_plugged": {name(t): int(n) for t, n in self.tunnels_plugged.items()},
            "handles_cut": {name(t): int(n) for t, n in self.handles_cut.items()},
            "genus_before": {name(t): int(n) for t, n in self.genus_before.items()},
            "genus_after": {name(t): int(n) for t, n in self.genus_after.items()},
        }

    def __str__(self) -> str:
        vox = "x".join(f"{v:g}" for v in self.voxel_mm)
        lines = [f"make_layers: {'x'.join(map(str, self.shape))} voxels of {vox} mm, "
                 f"{self.n_changed()} voxels relabelled"]
        for rule, c in self.changes.items():
            detail = ", ".join(f"{Tissue(a).name}->{Tissue(b).name} {n}"
                               for (a, b), n in sorted(c.items(), key=lambda kv: -kv[1]))
            lines.append(f"  {rule:<11s} {sum(c.values()):>9d}" + (f"  ({detail})" if detail else ""))
        dropped = ", ".join(f"{t.name} {n}" for t, n in self.dropped_components.items() if n)
        lines.append(f"  components dropped: {dropped or 'none'}")
        verb = "relabelled BRAIN" if self.ventricles == "brain" else "kept as CSF"
        lines.append(f"  ventricle CSF enclosed by brain: {self.ventricle_voxels} voxels ({verb})")
        lines.append(f"  nesting: {self.nesting} neighbours; thin skull/scalp parts: {self.thin}")
        lines.append("  closing radius mm: " + ", ".join(
            f"{t.name} {v:g}" for t, v in self.closing_radius_mm.items())
            + ("  (brain closed: the tunnel rule left it handles)" if self.brain_closed else ""))
        lines.append("  min thickness mm: " + ", ".join(
            f"{t.name} {v:g}" for t, v in self.min_thickness_mm.items()))
        for c in self.fov_cuts:
            lines.append(
                f"  field-of-view cut at {c['face']} ({c['side']}): {c['tissue_voxels']} tissue voxels "
                f"({', '.join(f'{k} {v}' for k, v in c['tissues'].items())}), "
                f"{c['area_mm2']:.0f} mm^2; closed, grid padded {c['pad_voxels']} voxels "
                f"({c['pad_mm']:g} mm)")
        if (any(self.tunnels_plugged.values()) or any(self.handles_cut.values())
                or any(self.genus_after.values())):
            lines.append("  tunnels plugged / handles cut: " + ", ".join(
                f"{t.name} {self.tunnels_plugged.get(t, 0)}/{self.handles_cut.get(t, 0)} (genus "
                f"{self.genus_before.get(t, 0)} -> {self.genus_after.get(t, 0)})" for t in TISSUES))
        lines.append("  volume cm^3 before -> after: " + ", ".join(
            f"{t.name} {self.volumes_before_mm3[t] / 1e3:.1f} -> {self.volumes_after_mm3[t] / 1e3:.1f}"
            for t in TISSUES))
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Morphology on a padded working grid (the grid always has a background margin wider than any
# structuring element, so cropping to a bounding box never cuts a structure).


def ball(radius_mm: float, voxel_mm) -> np.ndarray:
    """Digital ball: voxel offsets d with |d * voxel_mm| <= radius_mm, as a boolean structure.

    Arguments:
        radius_mm: ball radius in mm.
        voxel_mm: (3,) voxel edge lengths in mm (anisotropic voxels give an ellipsoid in index space).
    Returns:
        (2 r_x + 1, 2 r_y + 1, 2 r_z + 1) bool array, r_i = floor(radius_mm / voxel_mm[i]).
    """
    vox = np.broadcast_to(np.asarray(voxel_mm, dtype=np.float64), (3,))
    r = np.floor(radius_mm / vox + 1e-9).astype(int)
    grids = np.meshgrid(*[np.arange(-k, k + 1) * v for k, v in zip(r, vox)], indexing="ij")
    return (grids[0] ** 2 + grids[1] ** 2 + grids[2] ** 2) <= radius_mm ** 2 * (1 + 1e-9)


def _bbox(mask: np.ndarray, margin) -> tuple[slice, slice, slice] | None:
    """Bounding box of `mask` grown by `margin` voxels per axis (clipped), or None if empty."""
    margin = np.broadcast_to(np.asarray(margin, dtype=int), (3,))
    out = []
    for ax in range(3):
        other = tuple(a for a in range(3) if a != ax)
        idx = np.flatnonzero(mask.any(axis=other))
        if idx.size == 0:
            return None
        out.append(slice(max(idx[0] - margin[ax], 0), min(idx[-1] + margin[ax] + 1, mask.shape[ax])))
    return tuple(out)


def _dilate(mask: np.ndarray, st: np.ndarray) -> np.ndarray:
    out = np.zeros_like(mask)
    sl = _bbox(mask, np.array(st.shape) // 2 + 1)
    if sl is not None:
        out[sl] = ndi.binary_dilation(mask[sl], st)
    return out


def _erode(mask: np.ndarray, st: np.ndarray) -> np.ndarray:
    out = np.zeros_like(mask)
    sl = _bbox(mask, 1)
    if sl is not None:
        out[sl] = ndi.binary_erosion(mask[sl], st, border_value=0)
    return out


def _close(mask: np.ndarray, st: np.ndarray) -> np.ndarray:
    out = np.zeros_like(mask)
    sl = _bbox(mask, np.array(st.shape) // 2 * 2 + 2)
    if sl is not None:
        sub = mask[sl]
        out[sl] = ndi.binary_erosion(ndi.binary_dilation(sub, st), st, border_value=0) | sub
    return out


def _holes(mask: np.ndarray) -> np.ndarray:
    """Voxels outside `mask` not face-connected to the grid border (the cavities of `mask`)."""
    out = np.zeros_like(mask)
    sl = _bbox(mask, 1)
    if sl is None:
        return out
    sub = ~mask[sl]
    lab, n = ndi.label(sub, structure=_CROSS)
    if n > 1:
        # the bounding box has a 1-voxel margin outside `mask`, so its corner is outer background
        out[sl] = sub & (lab != lab[0, 0, 0])
    return out


def _components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """(voxels outside the largest face-connected component of `mask`, number of other components)."""
    largest, n = largest_component(mask)
    return (mask & ~largest if n else np.zeros_like(mask)), n


# ---------------------------------------------------------------------------------------------
# Input checks and padding


def _border_tissues(labels: np.ndarray) -> dict[Tissue, list[str]]:
    """Tissues with voxels on the grid's outer faces -> the faces ("x=0", "z=max", ...)."""
    found: dict[Tissue, list[str]] = {}
    for ax, axis in enumerate("xyz"):
        for end, tag in ((0, "0"), (-1, "max")):
            face = np.take(labels, end, axis=ax)
            for v in np.unique(face):
                if v != 0:
                    found.setdefault(Tissue(int(v)), []).append(f"{axis}={tag}")
    return found


def check_labels(labels: LabelMap, name: str = "labels", *, allow_border: bool = False) -> None:
    """Raise ValueError unless `labels` is a LabelMap with all four tissues, clear of the border.

    Arguments:
        labels: the label map to check.
        name: the argument name used in messages.
        allow_border: accept tissue on the volume border (a field-of-view cut that
            ``make_layers`` closes, ``LayerConfig.fov_cut="close"``).
    """
    if not isinstance(labels, LabelMap):
        raise ValueError(
            f"`{name}` must be a jaxhead.LabelMap, got {type(labels).__name__}; wrap an array "
            "as LabelMap(labels, affine).")
    lab = labels.labels
    if lab.size and (lab.min() < 0 or lab.max() > int(max(Tissue))):
        bad = np.unique(lab[(lab < 0) | (lab > int(max(Tissue)))])[:10].tolist()
        raise ValueError(
            f"`{name}` has labels {bad} outside 0..{int(max(Tissue))}; use Tissue values "
            "(0=BACKGROUND, 1=BRAIN, 2=CSF, 3=SKULL, 4=SCALP).")
    if lab.size == 0 or not np.any(lab):
        raise ValueError(
            f"`{name}` is empty (shape {lab.shape}, no tissue voxels); pass a label map with "
            "BRAIN=1, CSF=2, SKULL=3, SCALP=4 voxels.")
    counts = np.bincount(lab.ravel().astype(np.int64), minlength=len(Tissue))
    missing = [t.name for t in TISSUES if counts[int(t)] == 0]
    if missing:
        raise ValueError(
            f"`{name}` has no {', '.join(missing)} voxels; the nested head model needs all four "
            "tissues (BRAIN=1, CSF=2, SKULL=3, SCALP=4). Check the segmentation.")
    border = {} if allow_border else _border_tissues(lab)
    if border:
        where = "; ".join(f"{t.name} on {', '.join(faces)}" for t, faces in border.items())
        raise ValueError(
            f"`{name}` has tissue on the volume border ({where}): the layers would be cut open "
            "there. Let make_layers close the cut (LayerConfig(fov_cut='close'), the default), "
            "or pad the volume with background first, e.g. "
            "`jaxhead.geometry.layers.pad_labels(labels, 4)` (or numpy.pad with 0 and a shifted "
            "affine).")


def pad_labels(labels: LabelMap, n_voxels: int | tuple[int, int, int]) -> LabelMap:
    """Pad a label map with background on every side, keeping world positions of its voxels.

    Arguments:
        labels: the label map.
        n_voxels: voxels to add on each side, one int or one per axis (x, y, z).
    Returns:
        A LabelMap of shape (x + 2 n_x, y + 2 n_y, z + 2 n_z) whose affine is shifted by -n voxels.
    """
    n = np.broadcast_to(np.asarray(n_voxels), (3,))
    if not np.issubdtype(n.dtype, np.integer) or np.any(n < 0):
        raise ValueError(f"`n_voxels` must be non-negative integers, got {n_voxels!r}.")
    shift = np.eye(4)
    shift[:3, 3] = -n
    padded = np.pad(labels.labels, [(int(k), int(k)) for k in n], constant_values=0)
    return LabelMap(padded, labels.affine @ shift)


def _or_shifts(X: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """OR of X over the 2^len(axes) unit shifts along `axes` (cells shared by adjacent voxels)."""
    out = None
    for bits in range(1 << len(axes)):
        sl = [slice(None)] * 3
        for j, ax in enumerate(axes):
            sl[ax] = slice(1, None) if (bits >> j) & 1 else slice(None, -1)
        part = X[tuple(sl)]
        out = part if out is None else out | part
    return out


def euler_characteristic(mask: np.ndarray) -> int:
    """Euler characteristic of the union of the closed unit cubes of `mask` (V - E + F - C).

    For one solid without cavities it is 1 - genus (a ball: 1; a torus-like solid: 0). Closed
    cubes make diagonal (edge or corner) contacts connections, so a diagonal-only bridge counts as
    a handle: the conservative choice for surfaces, where such contacts pinch.

    Arguments:
        mask: (x, y, z) bool.
    Returns:
        The Euler characteristic (int).
    """
    X = np.pad(np.asarray(mask, dtype=bool), 1)
    cubes = int(X.sum())
    faces = sum(int(_or_shifts(X, (a,)).sum()) for a in range(3))
    edges = sum(int(_or_shifts(X, (a, b)).sum()) for a, b in ((0, 1), (0, 2), (1, 2)))
    verts = int(_or_shifts(X, (0, 1, 2)).sum())
    return verts - edges + faces - cubes


def _genus(solid: np.ndarray) -> int:
    """Handles of a one-component, cavity-free solid, counted both ways diagonal contacts can go.

    Closed cubes of the solid (its diagonal contacts connect): genus 1 - chi(solid). Closed
    cubes of the complement in the solid's box grown by one voxel (the complement's diagonal
    contacts connect, i.e. the solid is face-connected): that region's boundary is the box
    (a sphere) plus the solid's surface, so chi = (2 + 2 - 2 genus) / 2 and genus = 2 - chi.
    Marching cubes on a smoothed mask can resolve a diagonal contact either way, so a surface is
    a sphere for sure only when both are 0; the larger is returned.
    """
    sl = _bbox(solid, 1)
    if sl is None:
        return 0
    sub = solid[sl]
    return max(1 - euler_characteristic(sub), 2 - euler_characteristic(~sub), 0)


def _euler_gain(sub: np.ndarray, new: np.ndarray) -> int:
    """Change of chi(solid) + chi(complement) from `sub` to `new` (both conventions of :func:`_genus`)."""
    return (euler_characteristic(new) - euler_characteristic(sub)
            + euler_characteristic(~new) - euler_characteristic(~sub))


def _pieces(cand: np.ndarray, shape):
    """26-connected pieces of `cand`: (label array, [(window slices, piece mask in window)])."""
    lab, _ = ndi.label(cand, structure=_CUBE)
    out = []
    for i, sl in enumerate(ndi.find_objects(lab), start=1):
        if sl is not None:
            win = tuple(slice(max(a.start - 2, 0), min(a.stop + 2, m)) for a, m in zip(sl, shape))
            out.append((win, lab[win] == i))
    return out


def _link_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the 8 corners, 12 edges and 6 faces of the centre cube of a 3x3x3 block: the flat
    indices (into the block, C order) of the other cubes that share that cell."""
    d = np.indices((3, 3, 3)).reshape(3, -1).T - 1  # offset of each block cube
    signs = np.indices((2, 2, 2)).reshape(3, -1).T * 2 - 1  # (8, 3)

    def sharing(cell):  # cell: (3,) in {-1, 0, +1}; cube d shares it iff d_i in {0, cell_i}
        ok = np.all((d == 0) | (d == cell), axis=1) & np.any(d != 0, axis=1)
        return np.flatnonzero(ok)

    corners = np.array([sharing(c) for c in signs])
    pairs = np.indices((2, 2)).reshape(2, -1).T * 2 - 1  # (4, 2)
    edges = np.array([sharing(np.insert(c, a, 0)) for a in range(3) for c in pairs])
    faces = np.array([sharing(np.eye(3, dtype=int)[a] * sg) for a in range(3) for sg in (-1, 1)])
    return corners, edges, faces


_LINK = _link_tables()


def _link_chi(block: np.ndarray) -> int:
    """Euler characteristic of the centre closed cube of a 3x3x3 block intersected with the
    other closed cubes of the block that are set (vertices - edges + faces of the centre cube
    they cover). Adding the centre cube to a cube complex changes its Euler characteristic by
    1 - this; a point is simple (its addition changes no topology) when this is 1 for the solid
    and for the complement alike."""
    b = block.ravel()
    corners, edges, faces = _LINK
    return int(b[corners].any(axis=1).sum()) - int(b[edges].any(axis=1).sum()) + int(b[faces].sum())


def _thin_cut(sub: np.ndarray, piece: np.ndarray) -> np.ndarray:
    """The part of a cut `piece` (voxels to remove from the solid `sub`) that does the cutting.

    An opening removes a whole thin bar, not one cross-section of it. Voxels of the piece are
    given back to the solid, nearest the kept solid first (so the two ends grow towards each
    other), whenever they are simple points of the kept solid (:func:`_link_chi`: neither the
    solid's Euler characteristic nor its complement's changes, a test on the voxel's 26
    neighbours); what is left is a wall about one voxel thick where the fronts meet, with the
    piece's Euler gain. `piece` lies at least 2 voxels inside `sub`'s box.
    """
    return _peel(sub & ~piece, piece)


def _peel(grow: np.ndarray, piece: np.ndarray) -> np.ndarray:
    """What is left of `piece` after giving its simple points to `grow` (disjoint from it), nearest
    `grow` first, until none is left to give (:func:`_link_chi` is 1 for `grow` and for its
    complement alike: no Euler characteristic changes). Both arrays are copied."""
    piece = piece.copy()
    grow = grow.copy()
    idx = np.argwhere(piece)
    dist = ndi.distance_transform_edt(~grow)[tuple(idx.T)]
    idx = idx[np.argsort(dist, kind="stable")]
    changed = True
    while changed:
        changed = False
        for v in idx:
            i, j, k = v
            if not piece[i, j, k]:
                continue
            block = grow[i - 1:i + 2, j - 1:j + 2, k - 1:k + 2]
            if _link_chi(block) == 1 and _link_chi(~block) == 1:
                grow[i, j, k] = True
                piece[i, j, k] = False
                changed = True
    return piece


def _thin_plug(sub: np.ndarray, piece: np.ndarray) -> np.ndarray:
    """The part of a plug `piece` (voxels to add to the solid `sub`) that does the plugging.

    The dual of :func:`_thin_cut`. A closing proposes every voxel it fills, and where the
    solid's complement is a network of narrow channels (the sulcal CSF around the brain) one
    26-connected piece holds many of them, while only one cross-section of one channel closes
    the tunnel. Voxels of the piece are given back to the complement, nearest the kept
    complement first (so the channel is emptied from its ends inward), whenever they are simple
    points (:func:`_link_chi` is 1 for the complement and the solid alike: no Euler
    characteristic changes); what is left is a membrane about one voxel thick with the piece's
    Euler gain. `piece` lies at least 2 voxels inside `sub`'s box.
    """
    return _peel(~sub & ~piece, piece)


def _plug_tunnels(L: np.ndarray, k: int, vox, max_r: int, kept: np.ndarray | None,
                  fixed: np.ndarray | None = None) -> tuple[int, int]:
    """Make solid k = {1 <= L <= k} genus 0 in place: plug its tunnels, else cut its handles.

    Returns (pieces added, pieces cut).

    Plugs: closings of radius 1..max_r voxels (in mm: r * the largest voxel edge, a ball) propose
    voxels; each 26-connected piece is added (as label k) only if it raises the Euler
    characteristic of the solid plus that of its complement (both diagonal conventions of
    :func:`_genus`), computed on the piece's bounding box grown by 2 voxels: every cell a piece
    adds or removes lies within one voxel of it, so the difference there is the difference of the
    whole grid. For the brain (k = Tissue.BRAIN) the piece is first thinned to one cross-section
    (:func:`_thin_plug`, the same Euler gain) and widened by one voxel within the piece; the
    whole piece is added only if the widened part lost the gain.

    Cuts, for the handles no closing up to max_r plugs (a bar of the solid over an opening wider
    than 2 max_r voxels: thin bony bars of the face and skull base in the skull solid of a real
    head, a bridge of scalp over a wide crater of a fragmented segmentation): the dual, openings
    of radius 1..max_r propose voxels to remove from the solid, only voxels of the solid's own
    shell tissue outside `fixed` (the inner solid's nesting and thickness band, which rules 5
    and 6 would grow back), and a piece is removed (relabelled k + 1, background for the head)
    only if it raises the same Euler sum while the solid stays one face-connected component
    without cavities, i.e. exactly when it lowers the genus; only one cross-section of the piece
    is cut (:func:`_thin_cut`), widened to the opening's diameter (2 r + 1 voxels), so the gap is
    as wide as the bar was thin. Filling stays first: it seals a
    channel through a shell (what matters for current flow), where a cut would open one, and
    its results are those of the rule before cuts existed.
    This is the multiscale morphological topology correction of Han, Xu, Tosun & Prince (2002,
    IEEE TMI 21:109), foreground and background, with plugs preferred to cuts.
    """
    solid = (L >= 1) & (L <= k)
    if k == 1 and kept is not None:
        solid = solid | kept
    if _genus(solid) == 0:
        return 0, 0
    n_added = n_cut = 0
    radii = [ball(r * float(np.max(vox)), vox) for r in range(1, max_r + 1)]
    for st in radii:
        for win, piece in _pieces(_close(solid, st) & ~solid, L.shape):
            sub = solid[win]
            if _euler_gain(sub, sub | piece) <= 0:
                continue
            if k == Tissue.BRAIN:
                # the brain's complement is the CSF the rules keep: add one cross-section of
                # the channel, widened by one voxel (three voxels thick, thicker than rule
                # ``thin``'s two: a one-voxel sheet presmooths into a sliver), not the piece
                wide = _dilate(_thin_plug(sub, piece), _CROSS) & piece
                if _euler_gain(sub, sub | wide) > 0:
                    piece = wide
            solid[win] |= piece
            L[win][piece] = k
            n_added += 1
        if _genus(solid) == 0:
            return n_added, n_cut
    movable = L == k
    if fixed is not None:
        movable &= ~fixed
    for st in radii:
        opened = _dilate(_erode(solid, st), st)
        for win, piece in _pieces(solid & ~opened & movable, L.shape):
            piece &= solid[win]
            sub = solid[win]
            if not piece.any() or _euler_gain(sub, sub & ~piece) <= 0:
                continue
            # one cross-section, widened to the opening's diameter: a one-voxel slit is as
            # narrow as the tunnels this rule removes, and would knot the surface the same way
            piece = _dilate(_thin_cut(sub, piece), st) & piece
            if _euler_gain(sub, sub & ~piece) <= 0:
                continue
            trial = solid.copy()
            trial[win] &= ~piece
            if ndi.label(trial, structure=_CROSS)[1] != 1 or _holes(trial).any():
                continue
            solid = trial
            L[win][piece] = k + 1 if k < 4 else 0
            n_cut += 1
        if _genus(solid) == 0:
            break
    return n_added, n_cut


def _pad_to(st: np.ndarray, shape) -> np.ndarray:
    """Centre `st` in a zero array of `shape` (each axis at least st's; odd sizes)."""
    shape = np.maximum(np.array(st.shape), np.array(shape))
    out = np.zeros(tuple(shape), dtype=bool)
    off = (shape - np.array(st.shape)) // 2
    out[tuple(slice(o, o + n) for o, n in zip(off, st.shape))] = st
    return out


def _side_name(affine: np.ndarray, ax: int, end: int) -> str:
    """Anatomical direction (RAS world) of the outward normal of grid face (ax, end)."""
    d = affine[:3, ax] * (-1.0 if end == 0 else 1.0)
    w = int(np.argmax(np.abs(d)))
    return (("left", "right"), ("posterior", "anterior"), ("inferior", "superior"))[w][int(d[w] > 0)]


# ---------------------------------------------------------------------------------------------
# The rules


class _Ledger:
    """Accumulates (from, to) counts per rule as net changes of the label array."""

    def __init__(self):
        self.changes: dict[str, dict[tuple[Tissue, Tissue], int]] = {r: {} for r in RULES}
        self.dropped = {t: 0 for t in TISSUES}

    def record(self, rule: str, before: np.ndarray, after: np.ndarray) -> None:
        idx = before != after
        if not idx.any():
            return
        k = len(Tissue)
        pairs = np.bincount(before[idx].astype(np.int64) * k + after[idx], minlength=k * k)
        for code in np.flatnonzero(pairs):
            key = (Tissue(int(code) // k), Tissue(int(code) % k))
            self.changes[rule][key] = self.changes[rule].get(key, 0) + int(pairs[code])


def _fill_and_connect(L: np.ndarray, ledger: _Ledger, kept: np.ndarray | None,
                      fill: bool = True, connect: bool = True) -> None:
    """Fill cavities of every solid (inside out), then keep each one's largest component (outside in).

    Works in place on `L`. `kept` (ventricles="keep") marks CSF kept inside the brain: it counts as
    part of the brain solid, and CSF found in a new brain cavity joins it.
    """
    if fill:
        for k in (1, 2, 3, 4):
            solid = (L >= 1) & (L <= k)
            if k == 1 and kept is not None:
                solid |= kept
            holes = _holes(solid)
            if k == 1 and kept is not None:
                csf = holes & (L == int(Tissue.CSF))
                kept |= csf
                holes &= ~csf
            L[holes] = k
    if connect:
        for k in (4, 3, 2, 1):
            solid = (L >= 1) & (L <= k)
            if k == 1 and kept is not None:
                solid |= kept
            drop, n = _components(solid)
            if n:
                ledger.dropped[Tissue(k)] += n
                L[drop] = 0 if k == 4 else k + 1
                if k == 1 and kept is not None:
                    kept &= ~drop


def _shell_rule(L: np.ndarray, t: Tissue, st: np.ndarray, kept: np.ndarray | None) -> None:
    """Make shell `t` contain the dilation of its inner solid by `st` (in place).

    CSF takes the brain voxels it needs (the paper's brain erosion); SKULL and SCALP grow outward
    into the next tissue or background (the paper's skull = skull U brain U dilate(CSF)).
    """
    if t == Tissue.CSF:
        inner = L == int(Tissue.BRAIN)
        if kept is not None:
            inner |= kept
        outer = ((L >= 1) & (L <= 2)) | inner
        thin = inner & ~_erode(outer, st)
        L[thin] = int(Tissue.CSF)
        if kept is not None:
            kept &= ~thin
    else:
        k = int(t) - 1
        grow = _dilate((L >= 1) & (L <= k), st) & ((L == 0) | (L > int(t)))
        L[grow] = int(t)


def make_layers_reported(labels: LabelMap, cfg: LayerConfig = LayerConfig()) -> tuple[LabelMap, LayerReport]:
    """Clean a label map into four strictly nested layers and report every relabelled voxel.

    The rules and their order are in this module's docstring.

    Arguments:
        labels: (x, y, z) label map with BRAIN, CSF, SKULL and SCALP voxels. Tissue on the volume
            border is a field-of-view cut: closed when ``cfg.fov_cut == "close"``, else an error.
        cfg: the rule settings.
    Returns:
        (layers, report): the cleaned LabelMap and a LayerReport. The grid and affine are the
        input's, grown by ``report.padding`` where a cut was closed or a shell grew past the
        border (world positions of the input voxels are kept).
    """
    if not isinstance(cfg, LayerConfig):
        raise ValueError(f"`cfg` must be a LayerConfig, got {type(cfg).__name__}.")
    check_labels(labels, "labels", allow_border=cfg.fov_cut == "close")
    layers, report = _make_layers(labels, cfg)
    if cfg.closing_radius_mm is None and cfg.tunnels == "plug" and report.genus_after.get(Tissue.BRAIN, 0):
        # Fallback, counted in the report: the default leaves the brain unclosed (rule 1) and relies
        # on the tunnel rule, whose plugs and cuts are accepted piece by piece; a sulcal network can
        # leave handles no single piece removes (the MNI152 head at 1 mm segmented with another
        # head's atlas: genus 269 -> 2). The paper's closing of the brain as well removes them
        # there (genus 39 before the tunnel rule, 0 after), at the cost of sulcal CSF up to two
        # radii wide. Kept only if it leaves fewer handles.
        r = cfg.closing_radii(labels.voxel_mm)[Tissue.SCALP]
        closed, closed_report = _make_layers(labels, replace(cfg, closing_radius_mm=r))
        g0, g1 = sum(report.genus_after.values()), sum(closed_report.genus_after.values())
        log.warning("make_layers: the tunnel rule left the brain genus %d; closing the brain too (radius %g mm) "
                    "leaves genus %s: %s", report.genus_after[Tissue.BRAIN], r,
                    {t.name: g for t, g in closed_report.genus_after.items() if g} or 0,
                    "kept" if g1 < g0 else "not kept")
        if g1 < g0:
            return closed, replace(closed_report, brain_closed=True)
    return layers, report


def _make_layers(labels: LabelMap, cfg: LayerConfig) -> tuple[LabelMap, LayerReport]:
    """The rules of :func:`make_layers_reported` with these settings, once (no fallback)."""
    vox = labels.voxel_mm
    nest = _CROSS if cfg.nesting == "face" else _CUBE
    radii = cfg.closing_radii(vox)
    thick = cfg.thicknesses(vox)
    before_vol = labels.tissue_volumes_mm3()
    cuts = _border_tissues(labels.labels)

    # Work on a grid padded with background wide enough for every structuring element, for the
    # outward growth of skull and scalp and for the caps of a field-of-view cut (all three shells).
    grow_mm = thick[Tissue.CSF] + thick[Tissue.SKULL] + thick[Tissue.SCALP]
    pad = int(np.ceil(max(grow_mm + 2 * float(np.max(vox)), 2 * max(radii.values())) / vox.min())) + 4
    L = np.pad(labels.labels.astype(np.uint8), pad, constant_values=0)
    core = tuple(slice(pad, pad + n) for n in labels.shape)
    ledger = _Ledger()

    # 0. field-of-view cuts: cap each shell beyond every cut face, inside out
    prev = L.copy()
    faces = []
    if cuts:
        beyond = np.zeros(L.shape, dtype=bool)
        for ax in range(3):
            for end in (0, 1):
                face = np.take(labels.labels, 0 if end == 0 else -1, axis=ax)
                if not face.any():
                    continue
                sl = [slice(None)] * 3
                sl[ax] = slice(0, pad) if end == 0 else slice(pad + labels.shape[ax], None)
                beyond[tuple(sl)] = True
                counts = np.bincount(face.ravel().astype(np.int64), minlength=len(Tissue))
                area = float(np.prod(np.delete(vox, ax)))
                faces.append({"face": f"{'xyz'[ax]}={'0' if end == 0 else 'max'}",
                              "side": _side_name(labels.affine, ax, end), "axis": ax, "end": end,
                              "tissue_voxels": int(counts[1:].sum()),
                              "tissues": {t.name.lower(): int(counts[int(t)]) for t in TISSUES
                                          if counts[int(t)]},
                              "area_mm2": float(counts[1:].sum()) * area})
        for t in _SHELLS:
            st = _pad_to(ball(thick[t], vox), (3, 3, 3))
            st = st | _pad_to(nest, st.shape)  # at least the nesting rule
            inner = (L >= 1) & (L < int(t))
            add = _dilate(inner, st) & beyond & (L == 0)
            L[add] = int(t)
    ledger.record("fov", prev, L)

    # 1. closing of each tissue of the input; an outer layer's closing wins a contested voxel
    prev = L.copy()
    added = {}
    for t in TISSUES:
        st = ball(radii[t], vox)
        if st.sum() > 1:
            mask = prev == int(t)
            added[t] = _close(mask, st) & ~mask
    for t, add in added.items():  # TISSUES order: inside out, so the outer layer wins
        L[add] = int(t)
    ledger.record("closing", prev, L)

    # 2. ventricles: CSF in cavities of the brain
    prev = L.copy()
    cavity = _holes(L == int(Tissue.BRAIN))
    ventricle = cavity & (L == int(Tissue.CSF))
    n_ventricle = int(ventricle.sum())
    kept = None
    if cfg.ventricles == "brain":
        L[ventricle] = int(Tissue.BRAIN)
    else:
        kept = ventricle
    ledger.record("ventricles", prev, L)

    # 3. holes of every nested solid, inside out
    prev = L.copy()
    _fill_and_connect(L, ledger, kept, fill=True, connect=False)
    ledger.record("holes", prev, L)

    # 4. one component per nested solid, outside in
    prev = L.copy()
    _fill_and_connect(L, ledger, kept, fill=False, connect=True)
    ledger.record("components", prev, L)

    def solid(k):
        S = (L >= 1) & (L <= k)
        return S | kept if (k == 1 and kept is not None) else S

    genus_before = {Tissue(k): _genus(solid(k)) for k in (1, 2, 3, 4)}
    plugged = {t: 0 for t in TISSUES}
    cut = {t: 0 for t in TISSUES}
    # a shell's voxels within its nesting and thickness band of the inner solid are never
    # cut from it: rules 5 and 6 would grow them back
    band = {t: _pad_to(ball(thick[t], vox), (3, 3, 3)) | _pad_to(nest, ball(thick[t], vox).shape)
            for t in _SHELLS}

    def tunnels() -> bool:
        if cfg.tunnels != "plug":
            return False
        prev_t = L.copy()
        for k in (4, 3, 2, 1):
            fixed = _dilate(solid(k - 1), band[Tissue(k)]) if k > 1 else None
            n_plug, n_cut = _plug_tunnels(L, k, vox, cfg.max_tunnel_voxels, kept, fixed)
            plugged[Tissue(k)] += n_plug
            cut[Tissue(k)] += n_cut
        if np.array_equal(prev_t, L):
            return False
        _fill_and_connect(L, ledger, kept)
        ledger.record("tunnels", prev_t, L)
        return True

    def nesting(rule):
        prev_n = L.copy()
        for t in _SHELLS:
            _shell_rule(L, t, nest, kept)
        if not np.array_equal(prev_n, L):
            _fill_and_connect(L, ledger, kept)
        ledger.record(rule, prev_n, L)

    def thickness(rule):
        # balls contained in the nesting rule's structure are already satisfied by it
        prev_t = L.copy()
        for t in _SHELLS:
            st = ball(thick[t], vox)
            if max(st.shape) <= 3 and not (_pad_to(st, (3, 3, 3)) & ~nest).any():
                continue
            _shell_rule(L, t, st, kept)
        if not np.array_equal(prev_t, L):
            _fill_and_connect(L, ledger, kept)
        ledger.record(rule, prev_t, L)

    # 4a. thin parts of the skull and head solids
    if cfg.thin == "remove":
        prev = L.copy()
        for k in (4, 3):
            S = solid(k)
            sl = _bbox(S, 2)
            opened = np.zeros_like(S)
            opened[sl] = ndi.binary_opening(S[sl], _BLOCK)
            drop = S & ~opened & (L == k) & ~_dilate(solid(k - 1), band[Tissue(k)])
            L[drop] = k + 1 if k < 4 else 0
        if not np.array_equal(prev, L):
            _fill_and_connect(L, ledger, kept)
        ledger.record("thin", prev, L)
    # 4b. tunnels: every nested solid genus 0
    tunnels()
    # 5. strict nesting (face or 3x3x3 neighbours) for every shell, then clean up
    nesting("nesting")
    # 6. minimum thickness in mm
    thickness("thickness")
    # growth can bridge a groove: plug again, then restore nesting and thickness (twice at most)
    for _ in range(2):
        if not tunnels():
            break
        nesting("nesting")
        thickness("thickness")

    for t in TISSUES:
        if not np.any(L == int(t)):
            raise ValueError(
                f"make_layers removed every {t.name} voxel (the layer is thinner than the rules "
                "allow); check the segmentation or lower `min_thickness_mm`.")

    # Crop back to the input grid, grown where a cut was closed (fov_cut="close": also where a
    # shell grew past the border); with fov_cut="error" anything grown past the border is an error.
    if cfg.fov_cut == "close":
        box = _bbox(L.astype(bool), 1)
        crop = tuple(slice(min(c.start, b.start), max(c.stop, b.stop)) for c, b in zip(core, box))
    else:
        crop = core
        inside = np.zeros_like(L, dtype=bool)
        inside[core] = True
        outside = L.astype(bool) & ~inside
        border = _border_tissues(L[core])
        if outside.any() or border:
            sl = _bbox(L.astype(bool), 0)
            need = max(max(pad - s.start for s in sl),
                       max(s.stop - pad - n for s, n in zip(sl, labels.shape)))
            need = max(need, 0) + 1
            tissues = sorted({Tissue(int(v)) for v in np.unique(L[outside])} | set(border), key=int)
            raise ValueError(
                f"after growing the skull and scalp shells (strict nesting, minimum thickness), "
                f"{', '.join(t.name for t in tissues)} reaches the volume border; pad the label map "
                f"first, e.g. `pad_labels(labels, {need})`, set LayerConfig(fov_cut='close'), or "
                f"lower `min_thickness_mm`.")
    padding = tuple((int(core[a].start - crop[a].start), int(crop[a].stop - core[a].stop))
                    for a in range(3))
    out = L[crop]
    shift = np.eye(4)
    shift[:3, 3] = [-p[0] for p in padding]
    affine = labels.affine @ shift
    for f in faces:
        p = padding[f.pop("axis")][f.pop("end")]
        f["pad_voxels"] = int(p)
        f["pad_mm"] = float(p * vox[["x", "y", "z"].index(f["face"][0])])
    if faces:
        log.info("make_layers: field-of-view cut closed at %s", ", ".join(
            f"{f['face']} ({f['side']}, {f['tissue_voxels']} tissue voxels, padded {f['pad_voxels']})"
            for f in faces))

    if kept is not None:
        n_kept = int(kept[crop].sum())
    else:
        n_kept = 0
    genus_after = {Tissue(k): _genus(solid(k)) for k in (1, 2, 3, 4)}
    left = {t.name: g for t, g in genus_after.items() if g}
    if left and cfg.tunnels == "plug":
        log.warning("make_layers: handles kept (wider than max_tunnel_voxels=%d voxels to plug or "
                    "cut): %s", cfg.max_tunnel_voxels, ", ".join(f"{k} genus {g}" for k, g in left.items()))
    layers = LabelMap(out, affine)
    report = LayerReport(
        shape=tuple(int(s) for s in labels.shape),
        voxel_mm=tuple(float(v) for v in vox),
        changes={r: dict(c) for r, c in ledger.changes.items()},
        dropped_components=dict(ledger.dropped),
        ventricle_voxels=n_ventricle if cfg.ventricles == "brain" else n_kept,
        ventricles=cfg.ventricles,
        closing_radius_mm=dict(radii),
        min_thickness_mm=dict(thick),
        volumes_before_mm3=before_vol,
        volumes_after_mm3=layers.tissue_volumes_mm3(),
        fov_cuts=tuple(faces),
        padding=padding,
        tunnels_plugged=dict(plugged),
        handles_cut=dict(cut),
        genus_before=genus_before,
        genus_after=genus_after,
        nesting=cfg.nesting,
        thin=cfg.thin,
    )
    return layers, report


def make_layers(labels: LabelMap, cfg: LayerConfig = LayerConfig()) -> LabelMap:
    """Clean a label map into four strictly nested layers; the report is logged at INFO.

    Arguments:
        labels: (x, y, z) label map with all four tissues (see :func:`make_layers_reported`).
        cfg: the rule settings.
    Returns:
        The cleaned LabelMap (same grid and affine).
    """
    layers, report = make_layers_reported(labels, cfg)
    log.info("%s", report)
    return layers
