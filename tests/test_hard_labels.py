"""A corpus of hard label maps through make_layers + extract_surfaces, checked independently.

Each case is a small (~4 mm) label map that broke, or could break, the geometry: CSF one voxel
thin or missing, skull touching brain, a hole through the skull, fragmented scalp, a head cut by
the field of view (neck, skull base, vertex), anisotropic voxels, a real anatomy (the ANTs
young-adult head, ../shared/data/heads/README.md) and the demo's own MRI segmentation that used to
fail (tests/data/demo_mri_segment_2mm.nii.gz). Every case must give four surfaces that are

- closed, manifold, outward and free of self-intersections (trimesh's own watertight / winding
  checks, and :func:`check_surface`),
- nested: every vertex of an inner surface has generalised winding number 1 w.r.t. the next
  surface out and every vertex of the outer one winding number 0 w.r.t. the inner (computed here
  by summing exact triangle solid angles, Van Oosterom & Strackee 1983), with the exact
  triangle-triangle gap (manifold3d) at least ``min_gap_mm``,
- faithful: the enclosed volume of each surface is within ``VOLUME_TOL_VOXELS`` voxel edges
  times its area of the voxel volume of the solid it bounds (see the constant).

``experiments/hard_labels.py`` runs the same corpus at 2 mm and tables the repairs.
"""

import base64
import functools
import gzip
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from jaxhead import io
from jaxhead.geometry.layers import LayerConfig, euler_characteristic, make_layers_reported
from jaxhead.geometry.surface import (
    SurfaceConfig, check_surface, extract_surfaces_reported, surface_area_mm2, surface_gap_mm,
    surface_volume_mm3)
from jaxhead.phantom import make_head
from jaxhead.tissue import TISSUES, Tissue
from jaxhead.volume import LabelMap, default_affine

from shipped_heads import HEADS, needs_heads

DEMO_SEG = Path(__file__).resolve().parent / "data" / "demo_mri_segment_2mm.nii.gz"

#: |surface volume - voxel volume| <= VOLUME_TOL_VOXELS * voxel edge * surface area. The level-0.5
#: surface of a binary mask sits on the voxel faces on average (marching cubes on the 0.5-sigma
#: smoothed mask: exact for a plane); what moves it is Taubin smoothing (shrinks curved parts by
#: well under a voxel), the chordal sag of the remeshed triangles (h^2 / 8R: 0.1 mm for h = 6 mm,
#: R = 40 mm), the gap push (<= 1.1 min_gap_mm, only where shells are thin) and the repairs. A mean
#: normal offset of a quarter voxel is the bound: a systematic shift of a whole voxel would break
#: it four times over (at 4 mm on a 1.1e5 mm^2 scalp: 1.1e5 mm^3 against 3.6e6 mm^3, 3 %).
VOLUME_TOL_VOXELS = 0.25
#: 4 mm maps with the defaults scaled to them: edges of one voxel or more (the default 4-6 mm).
CFG4 = SurfaceConfig(edge_mm={"brain": 6.0, "csf": 4.0, "skull": 4.5, "scalp": 6.0})


# ---------------------------------------------------------------------------------------------
# The corpus: label-map generators (also used by experiments/hard_labels.py at 2 mm)


def _phantom(voxel_mm, seed=1, neck=True):
    _, labels = make_head("mri", voxel_mm=voxel_mm, seed=seed, neck=neck, noise=0.0, bias=False)
    return labels


def _world(labels: LabelMap) -> np.ndarray:
    ijk = np.indices(labels.shape).reshape(3, -1).T
    return (ijk @ labels.affine[:3, :3].T + labels.affine[:3, 3]).reshape(*labels.shape, 3)


def _crop(labels: LabelMap, sl) -> LabelMap:
    lo = np.array([s.start or 0 for s in sl], dtype=float)
    aff = labels.affine.copy()
    aff[:3, 3] = aff[:3, :3] @ lo + aff[:3, 3]
    return LabelMap(labels.labels[tuple(sl)].copy(), aff)


def _z_extent(labels: LabelMap, t: Tissue) -> tuple[int, int]:
    z = np.flatnonzero((labels.labels == int(t)).any(axis=(0, 1)))
    return int(z[0]), int(z[-1])


def case_phantom(vox):
    """The phantom's true labels (strictly nested already): the easy reference."""
    return _phantom(vox, seed=2)


def case_csf_thin_missing(vox):
    """CSF removed (brain touches skull) over the upper right quadrant, and one voxel thin
    (everything but the layer next to the skull given to brain) over the upper left."""
    lab = _phantom(vox)
    L, xyz = lab.labels.copy(), _world(lab)
    up = xyz[..., 2] > np.percentile(xyz[..., 2][L == int(Tissue.BRAIN)], 50)
    L[(L == int(Tissue.CSF)) & up & (xyz[..., 0] > 0)] = int(Tissue.BRAIN)
    csf = (L == int(Tissue.CSF)) & up & (xyz[..., 0] <= 0)
    from scipy import ndimage as ndi
    near_skull = ndi.binary_dilation(L == int(Tissue.SKULL), np.ones((3, 3, 3), bool))
    L[csf & ~near_skull] = int(Tissue.BRAIN)
    return LabelMap(L, lab.affine)


def case_skull_touches_brain(vox):
    """The CSF of the whole frontal half replaced by skull: skull directly on the brain."""
    lab = _phantom(vox, seed=3)
    L, xyz = lab.labels.copy(), _world(lab)
    L[(L == int(Tissue.CSF)) & (xyz[..., 1] > 10.0)] = int(Tissue.SKULL)
    return LabelMap(L, lab.affine)


def case_skull_hole(vox):
    """A 12 mm wide hole through the skull (filled with scalp) at the vertex, and a 2-voxel one
    (CSF) at the side: a scalp-CSF contact and a CSF channel through the bone."""
    lab = _phantom(vox)
    L, xyz = lab.labels.copy(), _world(lab)
    skull = L == int(Tissue.SKULL)
    L[skull & (np.hypot(xyz[..., 0], xyz[..., 1] + 10.0) < 6.0) & (xyz[..., 2] > 0)] = int(Tissue.SCALP)
    L[skull & (np.hypot(xyz[..., 1], xyz[..., 2] - 20.0) < vox) & (xyz[..., 0] > 0)] = int(Tissue.CSF)
    return LabelMap(L, lab.affine)


def case_fragmented_scalp(vox):
    """About a third of the scalp lost in random blobs (background), plus floating scalp specks."""
    lab = _phantom(vox)
    L = lab.labels.copy()
    rng = np.random.default_rng(0)
    from scipy import ndimage as ndi
    noise = ndi.gaussian_filter(rng.standard_normal(L.shape), 8.0 / vox)
    scalp = L == int(Tissue.SCALP)
    L[scalp & (noise > np.percentile(noise[scalp], 67))] = 0
    inside = np.zeros(L.shape, dtype=bool)
    inside[2:-2, 2:-2, 2:-2] = True  # specks in the volume, not on its border (not a FOV cut)
    specks = (L == 0) & inside & (rng.random(L.shape) < 0.002)
    L[specks] = int(Tissue.SCALP)
    return LabelMap(L, lab.affine)


def case_cut_neck(vox):
    """The field of view ends in the neck, below the skull: only scalp (neck) on z=0."""
    lab = _phantom(vox)
    z0, _ = _z_extent(lab, Tissue.SKULL)
    return _crop(lab, (slice(None), slice(None), slice(max(z0 - 3, 1), None)))


def case_cut_skull_base(vox):
    """A CT-like field of view through the skull base: skull, CSF and brain stem on z=0."""
    lab = _phantom(vox, seed=4)
    z0, _ = _z_extent(lab, Tissue.BRAIN)
    return _crop(lab, (slice(None), slice(None), slice(z0 + 2, None)))


def case_cropped_vertex(vox):
    """The top of the head cut off: brain, CSF, skull and scalp all on z=max."""
    lab = _phantom(vox)
    _, z1 = _z_extent(lab, Tissue.BRAIN)
    return _crop(lab, (slice(None), slice(None), slice(0, z1 - 1)))


def case_cut_face_and_side(vox):
    """Cut at the front (nose and forehead scalp) and on the right (scalp and skull)."""
    lab = _phantom(vox, seed=5)
    L = lab.labels
    y = np.flatnonzero(L.any(axis=(0, 2)))
    x = np.flatnonzero((L == int(Tissue.SKULL)).any(axis=(1, 2)))
    return _crop(lab, (slice(0, x[-1] - 1), slice(0, y[-1] - 3), slice(None)))


def case_anisotropic(vox):
    """Thick slices: 0.75 x `vox` in plane, 1.4 x `vox` between slices (and a neck cut)."""
    lab = _phantom((0.75 * vox, 0.75 * vox, 1.4 * vox), seed=6)
    z0, _ = _z_extent(lab, Tissue.SKULL)
    return _crop(lab, (slice(None), slice(None), slice(z0 + 1, None)))


@functools.lru_cache(maxsize=2)
def ants_head(vox: int = 4) -> LabelMap:
    """The ANTs 19.5-year head (1 mm probability maps) as labels at `vox` mm: block-averaged
    probabilities, argmax of c1+c2 (brain), c3 (CSF), c4 (skull), c5 (scalp), c6 (air). The field
    of view cuts the neck (z=0) and the right ear (x=max), as a real scan would."""
    probs = []
    for i in range(1, 7):
        d = json.loads((HEADS / f"c{i}ANTS19-5Years_head.jnii").read_text(), strict=False)
        a = d["NIFTIData"]
        raw = gzip.decompress(base64.b64decode(a["_ArrayZipData_"]))
        # row-major (JData default): checked against the anatomy (brain above the neck, CSF
        # around the brain, scalp outermost)
        probs.append(np.frombuffer(raw, np.uint8).reshape(a["_ArraySize_"]).astype(np.float32))
        affine = np.vstack([np.array(d["NIFTIHeader"]["Affine"], dtype=float), [0, 0, 0, 1]])
    n = [s // vox * vox for s in probs[0].shape]
    block = lambda p: p[:n[0], :n[1], :n[2]].reshape(  # noqa: E731
        n[0] // vox, vox, n[1] // vox, vox, n[2] // vox, vox).mean(axis=(1, 3, 5))
    p = [block(q) for q in probs]
    stack = np.stack([p[5], p[0] + p[1], p[2], p[3], p[4]])
    L = np.argmax(stack, axis=0).astype(np.uint8)
    aff = affine @ np.diag([vox, vox, vox, 1.0])
    aff[:3, 3] = affine[:3, 3] + affine[:3, :3] @ np.full(3, (vox - 1) / 2.0)  # block centres
    return LabelMap(L, aff)


def case_ants(vox):
    return ants_head(int(round(vox)))


def case_demo_segmentation(vox):
    """The demo's MRI segmentation (2 mm) that failed at surfaces; always at its own 2 mm."""
    return io.load_labels(DEMO_SEG)


CASES = {
    "phantom": case_phantom,
    "csf_thin_missing": case_csf_thin_missing,
    "skull_touches_brain": case_skull_touches_brain,
    "skull_hole": case_skull_hole,
    "fragmented_scalp": case_fragmented_scalp,
    "cut_neck": case_cut_neck,
    "cut_skull_base": case_cut_skull_base,
    "cropped_vertex": case_cropped_vertex,
    "cut_face_and_side": case_cut_face_and_side,
    "anisotropic": case_anisotropic,
    "ants": case_ants,
    "demo_segmentation": case_demo_segmentation,
}


# ---------------------------------------------------------------------------------------------
# Independent checks


def winding_numbers(points: np.ndarray, V: np.ndarray, F: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Generalised winding number of each point w.r.t. a closed triangle surface, by summing the
    exact solid angle of every triangle (Van Oosterom & Strackee 1983, IEEE TBME 30:125)."""
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk, None, :]
        a, b, c = A - p, B - p, C - p
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("...i,...i", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("...i,...i", a, b) * lc
               + np.einsum("...i,...i", b, c) * la + np.einsum("...i,...i", c, a) * lb)
        out[s:s + chunk] = 2.0 * np.arctan2(det, den).sum(axis=1) / (4 * np.pi)
    return out


def _probe(P: np.ndarray, Q: np.ndarray, n_near: int = 200, n_spread: int = 200) -> np.ndarray:
    """Vertices of P to test against the surface through Q: the `n_near` closest to Q (where
    nesting can fail) and `n_spread` evenly spread over the rest (the exact winding number costs
    one solid angle per point and triangle). surface_gap_mm checks every triangle pair."""
    from scipy.spatial import cKDTree
    d = cKDTree(Q).query(P)[0]
    near = np.argsort(d)[:n_near]
    spread = np.arange(0, len(P), max(len(P) // n_spread, 1))
    return P[np.union1d(near, spread)]


def one_component_no_cavity(S: np.ndarray) -> bool:
    """One face-connected component whose complement is one face-connected component too."""
    from scipy import ndimage as ndi
    return ndi.label(S)[1] == 1 and ndi.label(np.pad(~S, 1, constant_values=True))[1] == 1


def solid_voxels(labels: LabelMap, t: Tissue) -> int:
    from scipy import ndimage as ndi
    S = (labels.labels >= 1) & (labels.labels <= int(t))
    return int(ndi.binary_fill_holes(S).sum())


def check_case(name, labels, cfg=CFG4, layer_cfg=LayerConfig()):
    """make_layers + extract_surfaces on one case, every invariant checked; returns the reports."""
    layers, lrep = make_layers_reported(labels, layer_cfg)
    surfaces, srep = extract_surfaces_reported(layers, cfg)
    vox = float(np.max(layers.voxel_mm))
    vox_vol = abs(float(np.linalg.det(layers.affine[:3, :3])))
    # The voxel solids are balls (one component, no cavity, no handle), counted independently of
    # make_layers' own bookkeeping, except for the handles the report declares: make_layers
    # plugs or cuts every handle up to max_tunnel_voxels (the narrow ones remeshing would knot),
    # and keeps a wider one (a tunnel under a fragmented scalp) with a warning. The surface may
    # lose a kept handle to its presmoothing but never gains one, and never holds a handle the
    # report does not name.
    for t in TISSUES:
        S = (layers.labels >= 1) & (layers.labels <= int(t))
        assert one_component_no_cavity(S), (name, t)
        assert 0 <= 1 - euler_characteristic(S) <= lrep.genus_after[t], (name, t, "undeclared handle")
        if layer_cfg.tunnels == "plug" and lrep.genus_after[t]:
            assert lrep.genus_after[t] < lrep.genus_before[t], (name, t)
    for t, s in surfaces.items():
        tm = trimesh.Trimesh(s.vertices, s.faces, process=False)
        assert tm.is_watertight and tm.is_winding_consistent, (name, t)
        assert len(tm.split(only_watertight=False)) == 1, (name, t)
        assert 2 - 2 * lrep.genus_after[t] <= tm.euler_number <= 2, (name, t, "surface genus")
        chk = check_surface(s)
        assert chk.ok, (name, t, chk.problems())
        vol = surface_volume_mm3(s)
        assert vol == pytest.approx(tm.volume, rel=1e-9)
        target = solid_voxels(layers, t) * vox_vol
        assert abs(vol - target) <= VOLUME_TOL_VOXELS * vox * surface_area_mm2(s), (
            name, t, vol, target)
    for inner, outer in zip(TISSUES[:-1], TISSUES[1:]):
        si, so = surfaces[inner], surfaces[outer]
        w_in = winding_numbers(_probe(si.vertices, so.vertices), so.vertices, so.faces)
        w_out = winding_numbers(_probe(so.vertices, si.vertices), si.vertices, si.faces)
        assert np.all(np.abs(w_in - 1) < 1e-6), (name, inner, outer)
        assert np.all(np.abs(w_out) < 1e-6), (name, inner, outer)
        assert surface_gap_mm(si, so, search_mm=1.0) >= cfg.min_gap_mm * (1 - 1e-6), (name, inner)
    return layers, lrep, surfaces, srep


# ---------------------------------------------------------------------------------------------
# Tests


def test_winding_numbers_reference():
    """The checker itself: 1 inside, 0 outside, -1 inside a reversed surface (a box; points near
    a face and a corner included)."""
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    V, F = np.asarray(box.vertices), np.asarray(box.faces)
    pts = np.array([[0.0, 0, 0], [0.9, 0.9, -0.9], [0.999, 0.2, 0.1], [3.0, 0, 0], [1.001, 1.001, 1.001]])
    np.testing.assert_allclose(winding_numbers(pts, V, F), [1, 1, 1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(winding_numbers(pts, V, F[:, ::-1]), [-1, -1, -1, 0, 0], atol=1e-9)


@pytest.mark.parametrize("name", [n for n in CASES if n not in ("ants", "demo_segmentation")])
def test_hard_case(name):
    labels = CASES[name](4.0)
    layers, lrep, surfaces, srep = check_case(name, labels)
    cut = [c["face"] for c in lrep.fov_cuts]
    if name.startswith("cut_") or name in ("cropped_vertex", "anisotropic"):
        assert cut, name
        # the caps add only the shells' minimum thickness beyond each cut face (plus growth)
        assert all(c["pad_voxels"] <= 6 for c in lrep.fov_cuts), lrep.fov_cuts
    else:
        assert cut == [], name


@needs_heads
def test_ants_head_4mm():
    labels = ants_head(4)
    layers, lrep, surfaces, srep = check_case("ants", labels)
    # a real scan's field of view: the neck (inferior) is cut, and closed
    assert "inferior" in {c["side"] for c in lrep.fov_cuts}
    assert lrep.genus_after == {t: 0 for t in TISSUES}


def test_demo_segmentation_that_failed():
    """The demo's MRI segmentation that stopped at surfaces (3 self-intersecting CSF face pairs):
    its CSF and skull solids had handles; plugged, it meshes with the default settings."""
    labels = io.load_labels(DEMO_SEG)
    layers, lrep, surfaces, srep = check_case("demo_segmentation", labels, SurfaceConfig())
    assert lrep.genus_before[Tissue.CSF] > 0 and lrep.genus_after[Tissue.CSF] == 0
    assert lrep.tunnels_plugged[Tissue.CSF] > 0
    assert lrep.n_changed("tunnels") > 0


def test_fov_cut_caps_each_shell_at_min_thickness():
    """A neck cut through the skull base with min thicknesses of 2 voxels: beyond the cut plane,
    every shell is at least its minimum thickness (distance transform, independent of the rule)."""
    from scipy import ndimage as ndi
    labels = case_cut_skull_base(4.0)
    cfg = LayerConfig(min_thickness_mm={"csf": 8.0, "skull": 8.0, "scalp": 8.0})
    layers, rep = make_layers_reported(labels, cfg)
    assert [c["side"] for c in rep.fov_cuts] == ["inferior"]
    assert rep.fov_cuts[0]["tissues"].keys() >= {"brain", "skull", "scalp"}
    L = layers.labels
    for k, t in ((1, Tissue.CSF), (2, Tissue.SKULL), (3, Tissue.SCALP)):
        inner = (L >= 1) & (L <= k)
        d = ndi.distance_transform_edt(~inner, sampling=layers.voxel_mm)
        outer = (L >= 1) & (L <= k + 1)
        # every voxel within the thickness of the inner solid is in the next solid
        assert not ((d <= 8.0 + 1e-9) & ~outer).any(), t
    # world positions kept: the input's voxels are where they were
    pad = np.array([p[0] for p in rep.padding])
    np.testing.assert_allclose(layers.affine[:3, :3] @ pad + layers.affine[:3, 3], labels.affine[:3, 3])
    sl = tuple(slice(p, p + n) for p, n in zip(pad, labels.shape))
    same = layers.labels[sl] == labels.labels
    assert same.mean() > 0.9
    # fov_cut="error" refuses it, naming the faces and the fix
    with pytest.raises(ValueError, match=r"on the volume border.*z=0.*fov_cut='close'"):
        make_layers_reported(labels, LayerConfig(fov_cut="error"))


def test_fov_cut_report_and_config():
    labels = case_cut_neck(4.0)
    layers, rep = make_layers_reported(labels)
    d = rep.to_dict()
    json.dumps(d)
    (cut,) = d["fov_cuts"]
    assert cut["face"] == "z=0" and cut["side"] == "inferior" and cut["tissues"] == {"scalp": cut["tissue_voxels"]}
    assert cut["pad_mm"] == cut["pad_voxels"] * 4.0
    assert "field-of-view cut at z=0 (inferior)" in str(rep)
    assert rep.net_change(Tissue.SCALP, "fov") == 0  # scalp is outermost: nothing to cap
    assert layers.shape[2] == labels.shape[2] + sum(rep.padding[2])
    with pytest.raises(ValueError, match="fov_cut"):
        LayerConfig(fov_cut="pad")
    with pytest.raises(ValueError, match="tunnels"):
        LayerConfig(tunnels="fill")
    with pytest.raises(ValueError, match="max_tunnel_voxels"):
        LayerConfig(max_tunnel_voxels=0)


def test_euler_characteristic_reference():
    """Ball 1, solid torus 0, two balls 2, a ball with a cavity 2 (closed cubes)."""
    n = 20
    g = np.indices((n, n, n)) - n / 2 + 0.5
    r = np.sqrt((g ** 2).sum(0))
    ball = r < 6
    assert euler_characteristic(ball) == 1
    rho = np.hypot(g[0], g[1])
    torus = (rho - 5.5) ** 2 + g[2] ** 2 < 2.5 ** 2
    assert euler_characteristic(torus) == 0
    two = (np.sqrt(((g - np.array([5, 0, 0])[:, None, None, None]) ** 2).sum(0)) < 3) | (
        np.sqrt(((g + np.array([5, 0, 0])[:, None, None, None]) ** 2).sum(0)) < 3)
    assert euler_characteristic(two) == 2
    assert euler_characteristic(ball & (r > 3)) == 2


def _spheres(n: int, scalp_mm: float):
    """Concentric spheres on an n^3 grid of 3 mm voxels: (labels, affine, world xyz, radius)."""
    aff = default_affine(3.0, (n, n, n))
    ijk = np.indices((n, n, n)).reshape(3, -1).T
    xyz = (ijk @ aff[:3, :3].T + aff[:3, 3]).reshape(n, n, n, 3)
    r = np.linalg.norm(xyz, axis=-1)
    L = np.zeros((n, n, n), np.uint8)
    for rad, t in ((scalp_mm, 4), (42.0, 3), (33.0, 2), (27.0, 1)):
        L[r <= rad] = t
    return L, aff, xyz, r


def test_tunnel_through_skull_is_plugged():
    """A skull ring (a solid torus of skull solid around a scalp channel): genus 1 -> 0, the plug
    counted, and the surfaces spheres."""
    L, aff, xyz, r = _spheres(40, 50.0)
    # a 1-voxel channel of scalp through the skull solid's rim... make it a handle: a scalp hole
    # through a skull 'flap' that sticks out of the skull surface
    flap = (np.abs(xyz[..., 0]) < 3.5) & (xyz[..., 2] > 38) & (xyz[..., 2] < 48) & (np.abs(xyz[..., 1]) < 12)
    hole = flap & (np.abs(xyz[..., 1]) < 4) & (xyz[..., 2] > 42) & (xyz[..., 2] < 45.5)
    L[flap & ~hole] = 3
    L[hole] = 4
    L[(r > 42) & (r <= 50)] = np.where(L[(r > 42) & (r <= 50)] == 3, 3, 4)
    # the bar over the hole is one voxel thick: rule "thin" alone removes it (and the handle)
    _, rep_thin = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=0.0))
    assert rep_thin.genus_after == {t: 0 for t in TISSUES} and rep_thin.n_changed("thin") > 0
    layers, rep = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=0.0, thin="keep"))
    assert rep.genus_before[Tissue.SKULL] >= 1
    assert rep.genus_after == {t: 0 for t in TISSUES}
    assert rep.tunnels_plugged[Tissue.SKULL] >= 1
    assert rep.net_change(Tissue.SKULL, "tunnels") > 0
    surfaces, srep = extract_surfaces_reported(layers, SurfaceConfig(edge_mm=4.0))
    for s in surfaces.values():
        assert trimesh.Trimesh(s.vertices, s.faces, process=False).euler_number == 2


def test_handle_too_wide_to_plug_is_cut_at_one_cross_section():
    """A skull bar (an 'arch') over a scalp-filled opening 7 voxels wide: no closing of radius
    max_tunnel_voxels=2 plugs it, so the tunnel rule cuts the bar, one cross-section of it
    widened to at most 5 voxels (the bar is 3 x 3 voxels thick and 15 long), relabelled SCALP; genus 0
    after, the cut counted, and the rest of the bar still skull."""
    L, aff, xyz, r = _spheres(44, 60.0)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    # posts standing on the skull at y = -/+ 24 mm, joined at 52-61 mm above the centre (top bar)
    post = (np.abs(x) < 4.5) & (np.abs(np.abs(y) - 19.5) < 4.5) & (z > 30) & (z < 61)
    bar = (np.abs(x) < 4.5) & (np.abs(y) < 24) & (z > 52) & (z < 61)
    L[(post | bar) & (r > 42)] = 3
    L[(r > 42) & (r <= 70) & (L == 0) & (np.abs(x) < 20) & (np.abs(y) < 40) & (z > 20) & (z < 70)] = 4
    arch = (L == 3) & (r > 42)
    cfg = LayerConfig(closing_radius_mm=0.0, max_tunnel_voxels=2)
    layers, rep = make_layers_reported(LabelMap(L, aff), cfg)
    assert rep.genus_before[Tissue.SKULL] == 1
    assert rep.genus_after == {t: 0 for t in TISSUES}
    assert rep.handles_cut[Tissue.SKULL] == 1 and rep.tunnels_plugged[Tissue.SKULL] == 0
    cut = rep.changes["tunnels"].get((Tissue.SKULL, Tissue.SCALP), 0)
    # a wall across the 3 x 3 cross-section, widened to the opening's diameter (<= 5 voxels)
    assert 9 <= cut <= 5 * 9, cut
    assert "handles cut: " in str(rep) and rep.to_dict()["handles_cut"]["skull"] == 1
    # the rest of the arch is still skull
    core = layers.labels[tuple(slice(p[0], p[0] + s) for p, s in zip(rep.padding, L.shape))]
    assert (core[arch] == 3).sum() >= arch.sum() - cut
    S = (layers.labels >= 1) & (layers.labels <= 3)
    assert euler_characteristic(S) == 1 and one_component_no_cavity(S)
    # the same map with tunnels="keep": the handle stays, declared
    kept, rep_k = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=0.0, tunnels="keep"))
    assert rep_k.genus_after[Tissue.SKULL] == 1 and not any(rep_k.handles_cut.values())


def test_link_chi_is_the_local_euler_change():
    """The 3x3x3 simple-point test behind the cut thinning: adding a voxel changes the Euler
    characteristic of the closed-cube solid by 1 - link(solid neighbours), and of its complement
    by link(complement neighbours) - 1, on 2000 random neighbourhoods (checked with the global
    V - E + F - C count)."""
    from jaxhead.geometry.layers import _link_chi
    rng = np.random.default_rng(3)
    for _ in range(2000):
        b = rng.random((3, 3, 3)) < rng.random()
        b[1, 1, 1] = False
        w = np.pad(b, 1)
        w2 = w.copy()
        w2[2, 2, 2] = True
        assert euler_characteristic(w2) - euler_characteristic(w) == 1 - _link_chi(b)
        c = np.zeros((5, 5, 5), bool)
        c[1:4, 1:4, 1:4] = ~b
        c[2, 2, 2] = True
        c2 = c.copy()
        c2[2, 2, 2] = False
        assert euler_characteristic(c2) - euler_characteristic(c) == _link_chi(~b) - 1


def test_brain_tunnel_plug_is_one_cross_section_of_the_channel():
    """A brain block pierced by a straight CSF channel one voxel wide and 16 long (genus 1): the
    radius-1 closing proposes the whole channel, the plug keeps one cross-section widened by one
    voxel (3 channel voxels), so 13 CSF voxels stay CSF; the brain solid is genus 0 after. The
    skull solid (a shell's channel, sealed for current flow) still takes the whole piece."""
    from jaxhead.geometry.layers import _genus, _plug_tunnels
    L = np.zeros((30, 30, 30), np.uint8)
    L[4:26, 4:26, 4:26] = 2
    L[7:23, 7:23, 7:23] = 1
    L[15, 15, 7:23] = 2  # the channel, open to the CSF at both ends
    channel = np.zeros(L.shape, bool)
    channel[15, 15, 7:23] = True
    assert _genus((L >= 1) & (L <= 1)) == 1
    B = L.copy()
    n_plug, n_cut = _plug_tunnels(B, 1, np.array([2.0, 2.0, 2.0]), 4, None)
    assert (n_plug, n_cut) == (1, 0)
    assert _genus(B == 1) == 0
    filled = int((B[channel] == 1).sum())
    assert filled == 3, filled
    assert (B[~channel] == L[~channel]).all()
    # the same block as the skull solid (labels shifted out by two): the whole channel is filled
    S = np.where(L > 0, L + 2, 0).astype(np.uint8)
    S[S == 4] = 4
    n_plug, _ = _plug_tunnels(S, 3, np.array([2.0, 2.0, 2.0]), 4, None)
    assert n_plug == 1 and (S[channel] == 3).sum() >= 14
