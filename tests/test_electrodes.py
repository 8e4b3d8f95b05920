"""Electrodes type and placement on a sphere mesh: geometry against analytic positions."""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead.electrodes import (
    TEN_TEN,
    TEN_TWENTY,
    Electrodes,
    electrode_refinement_points,
    estimate_landmarks,
    layout_positions,
    place_electrodes,
    spread_positions,
)
from sphere_mesh import structured_sphere_mesh

R = 96.0
H = 10.0  # grid spacing in mm: boundary faces of ~7 mm edges


@pytest.fixture(scope="module")
def mesh():
    return structured_sphere_mesh((R,), h_mm=H)


@pytest.fixture(scope="module")
def face_size(mesh):
    """Largest centroid-to-vertex distance of a boundary face (mm)."""
    f, _ = mesh.boundary_faces()
    p = mesh.nodes[f]
    return float(np.linalg.norm(p - p.mean(axis=1, keepdims=True), axis=2).max())


def max_face_area(mesh):
    f, _ = mesh.boundary_faces()
    p = mesh.nodes[f]
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).max())


LANDMARKS = {"nasion": [0, R, 0], "inion": [0, -R, 0], "lpa": [-R, 0, 0], "rpa": [R, 0, 0]}


def _sph(polar_deg, azim_deg):
    t, p = np.radians(polar_deg), np.radians(azim_deg)
    return R * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def _arc_point(p, q, via_plane, frac):
    """Point at fraction `frac` along the arc p->q of the circle cut from the sphere by the
    plane through p, q and via_plane (independent of the mesh: pure sphere geometry)."""
    n = np.cross(q - p, via_plane - p)
    n /= np.linalg.norm(n)
    o = n * (p @ n)  # centre of the small circle
    a, b = p - o, q - o
    rho = np.linalg.norm(a)
    e1 = a / rho
    e2 = np.cross(n, e1)
    if (via_plane - o) @ e2 < 0:
        e2 = -e2
    ang = np.arctan2(b @ e2, b @ e1) % (2 * np.pi)
    t = frac * ang
    return o + rho * (np.cos(t) * e1 + np.sin(t) * e2)


def _analytic_ten_ten():
    """10-10 positions on a sphere from the Oostenveld & Praamstra rules, by hand."""
    P = {}
    mid = ["Fpz", "AFz", "Fz", "FCz", "Cz", "CPz", "Pz", "POz", "Oz"]
    for i, nm in enumerate(mid):  # midline great circle nasion (front) -> inion, 18 deg steps
        P[nm] = _sph(90 - 18 * (i + 1), 90) if i < 4 else _sph(18 * (i - 4), -90)
    cor = ["T7", "C5", "C3", "C1", "Cz", "C2", "C4", "C6", "T8"]
    for i, nm in enumerate(cor):
        P[nm] = _sph(72 - 18 * i, 180) if i < 4 else _sph(18 * (i - 4), 0)
    ring = ["AF", "F", "FT", "T", "TP", "P", "PO"]
    for i, r in enumerate(ring):  # the 10 % ring at polar 72 deg, 18 deg azimuth steps
        P.setdefault(f"{r}7", _sph(72, 90 + 18 * (i + 2)))
        P.setdefault(f"{r}8", _sph(72, 90 - 18 * (i + 2)))
    P["Fp1"], P["Fp2"] = _sph(72, 108), _sph(72, 72)
    P["O1"], P["O2"] = _sph(72, -108), _sph(72, -72)
    rows = {"AF": [(0.5, "3", "4")], "PO": [(0.5, "3", "4")]}
    for r in ("F", "FC", "CP", "P"):
        rows[r] = [(0.25, "5", "6"), (0.5, "3", "4"), (0.75, "1", "2")]
    lat = {"AF": "AF", "F": "F", "FC": "FT", "CP": "TP", "P": "P", "PO": "PO"}
    for r, items in rows.items():
        left, right, m = P[f"{lat[r]}7"], P[f"{lat[r]}8"], P[f"{r}z"]
        for f, ln, rn in items:
            P[f"{r}{ln}"] = _arc_point(left, m, right, f)
            P[f"{r}{rn}"] = _arc_point(right, m, left, f)
    return P


# ---------------------------------------------------------------------------------------------
# the Electrodes type


def _simple():
    return dict(centres=np.zeros((2, 3)), faces=np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]]),
                face_electrode=np.array([0, 0, 1]), contact_impedance_ohm_m2=0.01)


def test_electrodes_type_basics():
    e = Electrodes(**_simple())
    assert e.n_elec == 2
    assert e.names == ("E1", "E2")
    np.testing.assert_array_equal(e.contact_impedance_ohm_m2, [0.01, 0.01])
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 2, 0.0]])
    np.testing.assert_allclose(e.area_mm2(nodes), [1.0, 0.5])
    with pytest.raises(ValueError, match="area_mm2"):
        e.area_mm2()
    # a pytree: contact impedance can be swapped and traced
    e2 = eqx.tree_at(lambda x: x.contact_impedance_ohm_m2, e, jnp.array([0.02, 0.03]))
    f = jax.jit(lambda el: jnp.sum(el.contact_impedance_ohm_m2))
    assert float(f(e2)) == pytest.approx(0.05)


@pytest.mark.parametrize("change,match", [
    (dict(centres=np.zeros((2, 2))), "centres"),
    (dict(faces=np.array([[0, 1], [1, 2], [2, 3]])), "faces"),
    (dict(faces=np.array([[0, 1, -2], [1, 2, 3], [2, 3, 4]])), "negative"),
    (dict(face_electrode=np.array([0, 0])), "one electrode index per face"),
    (dict(face_electrode=np.array([0, 0, 2])), "0-based electrode"),
    (dict(face_electrode=np.array([0, 0, 0])), r"electrodes \[1\] have no faces"),
    (dict(contact_impedance_ohm_m2=-1.0), "contact_impedance_ohm_m2"),
    (dict(contact_impedance_ohm_m2=np.array([0.01, np.nan])), "contact_impedance_ohm_m2"),
    (dict(contact_impedance_ohm_m2=np.array([0.01, 0.01, 0.01])), "contact_impedance_ohm_m2"),
    (dict(names=("a",)), "names"),
    (dict(names=("a", "a")), "duplicates"),
])
def test_electrodes_validation(change, match):
    kw = _simple() | change
    with pytest.raises(ValueError, match=match):
        Electrodes(**kw)


# ---------------------------------------------------------------------------------------------
# placement


def test_positions_projected_onto_scalp(mesh, face_size):
    dirs = np.array([[0, 0, 1.0], [1, 0, 0], [0, -1, 0.2], [-0.5, 0.5, 0.7]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radius = 10.0
    e = place_electrodes(mesh, dirs * (R + 5.0), radius_mm=radius, contact_impedance_ohm_m2=0.01)
    r = np.linalg.norm(e.centres, axis=1)
    # on the polyhedral sphere: between the inscribed face planes and R (sagitta <= s^2 / 2R)
    assert np.all(r <= R + 1e-9) and np.all(r >= R - face_size**2 / (2 * R) - 1e-9)
    np.testing.assert_allclose(e.centres / r[:, None], dirs, atol=face_size / R)
    # area: the disc grows face by face and stops closest to pi r^2, so it is off by at most
    # half of the largest face
    area = e.area_mm2()
    np.testing.assert_allclose(area, e.area_mm2(mesh.nodes))
    assert np.all(np.abs(area - np.pi * radius**2) <= 0.5 * max_face_area(mesh)), area
    # faces are outward boundary faces within the disc
    p = mesh.nodes[e.faces]
    cen = p.mean(axis=1)
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", nrm, cen) > 0)
    # round: every face centroid within a face size of the rim
    d = np.linalg.norm(cen - e.centres[e.face_electrode], axis=1)
    assert np.all(d <= radius + face_size)
    np.testing.assert_array_equal(e.contact_impedance_ohm_m2, 0.01)
    assert e.names == ("E1", "E2", "E3", "E4")


def test_per_electrode_radius_and_impedance(mesh):
    pos = np.array([[0, 0, R], [R, 0, 0]])
    e = place_electrodes(mesh, pos, radius_mm=[8.0, 16.0], contact_impedance_ohm_m2=[0.01, 0.05],
                         names=["a", "b"])
    a = e.area_mm2()
    np.testing.assert_allclose(a, np.pi * np.array([8.0, 16.0]) ** 2,
                               atol=0.5 * max_face_area(mesh))
    np.testing.assert_array_equal(e.contact_impedance_ohm_m2, [0.01, 0.05])
    assert e.names == ("a", "b")


def test_tiny_radius_takes_face_under_centre_and_warns(mesh):
    with pytest.warns(UserWarning, match="too coarse"):
        e = place_electrodes(mesh, np.array([[0.0, 0, R], [0, R, 0]]), radius_mm=0.1)
    np.testing.assert_array_equal(np.bincount(e.face_electrode), [1, 1])


def test_overlap_is_an_error(mesh):
    pos = np.array([[0, 0, R], [3.0, 0, R], [R, 0, 0]])
    with pytest.raises(ValueError, match=r"overlap.*E1-E2"):
        place_electrodes(mesh, pos, radius_mm=5.0)


def test_touching_discs_are_an_error(mesh):
    # two discs that do not overlap (centres > 2 r apart) but lie in the same ~7 mm face
    f, _ = mesh.boundary_faces()
    v = mesh.nodes[f[0]]
    c = v.mean(axis=0)
    pos = np.array([c + 0.3 * (v[0] - c), c + 0.3 * (v[1] - c)])
    r = 0.45 * np.linalg.norm(pos[0] - pos[1])
    with pytest.warns(UserWarning, match="too coarse"):
        with pytest.raises(ValueError, match="share scalp faces"):
            place_electrodes(mesh, pos, radius_mm=r)


def test_far_position_is_an_error(mesh):
    pos = np.array([[0, 0, R], [0, 0, -R - 30.0]])
    with pytest.raises(ValueError, match=r"E2 \(30\.0 mm\)"):
        place_electrodes(mesh, pos)
    place_electrodes(mesh, pos, radius_mm=8.0, max_distance_mm=31.0)


@pytest.mark.parametrize("kw,match", [
    (dict(positions=np.zeros((3, 2))), "positions"),
    (dict(positions=np.zeros((2, 3)) + np.nan), "NaN"),
    (dict(positions=np.array([[0, 0, R]]), radius_mm=-1.0), "radius_mm"),
    (dict(positions=np.array([[0, 0, R]]), contact_impedance_ohm_m2=0.0), "contact_impedance_ohm_m2"),
    (dict(positions=np.array([[0, 0, R]]), names=["a", "b"]), "names"),
    (dict(positions="10-30"), "unknown layout"),
    (dict(positions=["Cz", "Xy9"]), "unknown electrode names"),
    (dict(positions=0), "positive int"),
    (dict(positions="10-20", landmarks={"nasion": [0, R, 0]}), "lacks"),
    (dict(positions="10-20", names=["a"]), "only for coordinate"),
])
def test_placement_errors(mesh, kw, match):
    with pytest.raises(ValueError, match=match):
        place_electrodes(mesh, **kw)


# ---------------------------------------------------------------------------------------------
# layouts


def test_estimated_landmarks_on_sphere(mesh):
    lm = estimate_landmarks(mesh)
    for k, v in LANDMARKS.items():
        np.testing.assert_allclose(lm[k], v, atol=1.0)  # sagitta of ~7 mm faces: < 0.3 mm


def test_ten_ten_matches_sphere_geometry(mesh):
    names, pos = layout_positions(mesh, "10-10", landmarks=LANDMARKS)
    assert names == TEN_TEN and len(names) == 61
    ref = _analytic_ten_ten()
    # the mesh is a polyhedron within ~0.3 mm of the sphere and arcs are traced with 0.25 deg
    # steps, so positions agree to ~1 % of the radius
    for nm, p in zip(names, pos):
        assert np.linalg.norm(p - ref[nm]) < 1.0, (nm, p, ref[nm])
    np.testing.assert_allclose(pos[names.index("Cz")], [0, 0, R], atol=0.5)


def test_ten_twenty_names_and_aliases(mesh):
    names, pos = layout_positions(mesh, "10-20", landmarks=LANDMARKS)
    assert names == TEN_TWENTY and len(names) == 21
    old, pos_old = layout_positions(mesh, ["T3", "T4", "T5", "T6"], landmarks=LANDMARKS)
    _, pos_new = layout_positions(mesh, ["T7", "T8", "P7", "P8"], landmarks=LANDMARKS)
    assert old == ("T3", "T4", "T5", "T6")
    np.testing.assert_allclose(pos_old, pos_new)


def test_layout_follows_landmarks_under_rigid_motion():
    # move the head: rotate about an oblique axis and shift; positions must move with it
    ang = np.radians(25.0)
    ax = np.array([1.0, 2.0, 0.5])
    ax /= np.linalg.norm(ax)
    K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    rot = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
    shift = np.array([10.0, -5.0, 20.0])
    m0 = structured_sphere_mesh((R,), h_mm=H)
    from jaxhead.geometry import TetMesh

    m1 = TetMesh(m0.nodes @ rot.T + shift, m0.tets, m0.labels)
    lm1 = {k: np.asarray(v, float) @ rot.T + shift for k, v in LANDMARKS.items()}
    _, p0 = layout_positions(m0, "10-20", landmarks=LANDMARKS)
    _, p1 = layout_positions(m1, "10-20", landmarks=lm1)
    np.testing.assert_allclose(p1, p0 @ rot.T + shift, atol=0.5)


def test_place_ten_twenty(mesh):
    e = place_electrodes(mesh, "10-20", landmarks=LANDMARKS, radius_mm=8.0)
    assert e.names == TEN_TWENTY
    assert e.n_elec == 21 and np.all(e.area_mm2() > 0)


def test_spread_positions_even_over_upper_head(mesh):
    n = 32
    p = spread_positions(mesh, n, landmarks=LANDMARKS)
    polar = np.degrees(np.arccos(p[:, 2] / np.linalg.norm(p, axis=1)))
    assert np.all(polar <= 72.0 + 1.0)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(n) * 1e9
    nn = d.min(axis=1)
    # equal-area spiral: every point's nearest neighbour is close to the spacing of a
    # hexagonal packing of the cap area (2 pi R^2 (1 - cos 72) / n per point)
    spacing = np.sqrt(2 * np.pi * R**2 * (1 - np.cos(np.radians(72))) / n * 2 / np.sqrt(3))
    assert nn.min() > 0.6 * spacing and nn.max() < 1.3 * spacing, (nn / spacing)
    e = place_electrodes(mesh, n, landmarks=LANDMARKS)
    np.testing.assert_allclose(e.centres, p, atol=1e-9)


def test_refinement_points(mesh):
    e = place_electrodes(mesh, np.array([[0, 0, R], [R, 0, 0]]), radius_mm=10.0)
    pts, edge = electrode_refinement_points(e, mesh.nodes)
    assert pts.shape == (18, 3) and edge.shape == (18,)
    r_eq = np.sqrt(e.area_mm2() / np.pi)
    np.testing.assert_allclose(edge, np.repeat(r_eq / 2, 9))
    ring = pts.reshape(2, 9, 3)
    dist = np.linalg.norm(ring[:, 1:] - e.centres[:, None], axis=2)
    np.testing.assert_allclose(dist, np.repeat(r_eq[:, None], 8, axis=1))
    # the ring lies in the tangent plane: perpendicular to the radial direction
    radial = e.centres / np.linalg.norm(e.centres, axis=1, keepdims=True)
    tang = np.einsum("eij,ej->ei", ring[:, 1:] - e.centres[:, None], radial)
    assert np.abs(tang).max() < 0.05 * r_eq.max()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        electrode_refinement_points(e, mesh.nodes, edge_mm=2.0)


def test_layout_on_scalp_surface_before_meshing(mesh):
    # positions can come from the scalp Surface (to refine the mesher there): same as on the
    # mesh whose boundary that surface is
    from jaxhead.geometry.surface import Surface

    f, _ = mesh.boundary_faces()
    scalp = Surface(mesh.nodes, f, "scalp")
    names, p_surf = layout_positions(scalp, "10-20", landmarks=LANDMARKS)
    _, p_mesh = layout_positions(mesh, "10-20", landmarks=LANDMARKS)
    np.testing.assert_allclose(p_surf, p_mesh, atol=1e-9)
    np.testing.assert_allclose(spread_positions(scalp, 8, landmarks=LANDMARKS),
                               spread_positions(mesh, 8, landmarks=LANDMARKS), atol=1e-9)
    with pytest.raises(ValueError, match="TetMesh"):
        place_electrodes(scalp, "10-20")


def test_electrode_config(mesh):
    from jaxhead.electrodes import ElectrodeConfig, electrodes_from_config

    cfg = ElectrodeConfig(layout=("Cz", "T7", "T8"), radius_mm=8.0,
                          contact_impedance_ohm_m2=0.05, landmarks_mm=LANDMARKS)
    e = electrodes_from_config(mesh, cfg)
    assert e.names == ("Cz", "T7", "T8")
    np.testing.assert_array_equal(e.contact_impedance_ohm_m2, 0.05)
    np.testing.assert_allclose(e.centres[0], [0, 0, R], atol=0.5)
    for kw, match in ((dict(layout="10-30"), "unknown layout"), (dict(layout=0), "positive int"),
                      (dict(radius_mm=0.0), "radius_mm"),
                      (dict(contact_impedance_ohm_m2=float("nan")), "contact_impedance_ohm_m2"),
                      (dict(landmarks_mm={"nasion": (0, 1, 0)}), "lacks")):
        with pytest.raises(ValueError, match=match):
            ElectrodeConfig(**kw)


@pytest.mark.parametrize("layout", [("Cz", "T7", "T8"), 12])
def test_electrode_positions_match_placed_centres(mesh, layout):
    # What the mesh stage refines at (from the scalp Surface, before meshing) is where
    # electrodes_from_config later puts the discs on the mesh.
    from jaxhead.electrodes import ElectrodeConfig, electrode_positions, electrodes_from_config
    from jaxhead.geometry.surface import Surface

    cfg = ElectrodeConfig(layout=layout, radius_mm=6.0, landmarks_mm=LANDMARKS)
    f, _ = mesh.boundary_faces()
    pos = electrode_positions(Surface(mesh.nodes, f, "scalp"), cfg)
    e = electrodes_from_config(mesh, cfg)
    assert pos.shape == (e.n_elec, 3)
    # centres are the positions projected onto the same triangles: equal to round-off
    np.testing.assert_allclose(pos, e.centres, atol=1e-6)
    with pytest.raises(ValueError, match="refine_mesh"):
        ElectrodeConfig(refine_mesh="yes")


# ---------------------------------------------------------------------------------------------
# Extended names, mixed names and coordinates, registration, landmark files (issue 15)

from jaxhead.electrodes import (  # noqa: E402
    EXTENDED,
    landmark_report,
    load_landmarks,
    register_positions,
)

UCL = ["Fp1", "Fp2", "F7", "F3", "Fz", "F4", "F8", "FC5", "FC1", "FC2", "FC6", "T7", "C3", "Cz",
       "C4", "T8", "CP5", "CP1", "CP2", "CP6", "P7", "P3", "Pz", "P4", "P8", "TP9", "TP10", "O1",
       "Oz", "O2", "I1", "I2", "NFpz"]


def test_extended_names_match_sphere_geometry(mesh):
    names, pos = layout_positions(mesh, list(EXTENDED) + ["I1", "I2"], landmarks=LANDMARKS)
    got = dict(zip(names, pos))
    # the 0 % ring is the equator (landmarks on it), cut at 10 % steps from Nz (+y) through
    # T9 (-x) to Iz (-y): fraction f sits 180 f degrees from +y (T9 at 50 %, TP9 60 %, O9 90 %)
    ring = ("AF", "F", "FT", "T", "TP", "P", "PO", "O")
    for k, r in enumerate(ring):
        a = np.radians(18.0 * (k + 2))  # AF9 at 20 %, as AF7 on the 10 % ring
        np.testing.assert_allclose(got[f"{r}9"], R * np.array([-np.sin(a), np.cos(a), 0]), atol=1.0)
        np.testing.assert_allclose(got[f"{r}10"], R * np.array([np.sin(a), np.cos(a), 0]), atol=1.0)
    np.testing.assert_allclose(got["I1"], got["O9"])  # I1/I2 are O9/O10 (UCL's names)
    np.testing.assert_allclose(got["Nz"], [0, R, 0], atol=1.0)
    np.testing.assert_allclose(got["Iz"], [0, -R, 0], atol=1.0)
    # the midline 10-5 points: NFpz at 5 % (9 deg above the nasion), ..., OIz at 95 %
    np.testing.assert_allclose(got["NFpz"], R * np.array([0, np.cos(np.radians(9)),
                                                          np.sin(np.radians(9))]), atol=1.0)
    np.testing.assert_allclose(got["CCPz"], R * np.array([0, -np.sin(np.radians(9)),
                                                          np.cos(np.radians(9))]), atol=1.0)
    with pytest.raises(ValueError, match="unknown electrode names"):
        layout_positions(mesh, ["TP11"], landmarks=LANDMARKS)


def test_ucl_montage_and_mixed_names_and_coordinates(mesh):
    el = place_electrodes(mesh, UCL, radius_mm=5.0, landmarks=LANDMARKS)
    assert el.names == tuple(UCL) and el.n_elec == 33
    xyz = _sph(60.0, 200.0)
    mixed = place_electrodes(mesh, ["Cz", tuple(xyz), "TP9"], radius_mm=5.0,
                             landmarks=LANDMARKS)
    assert mixed.names == ("Cz", "E2", "TP9")
    np.testing.assert_allclose(mixed.centres[0], el.centres[UCL.index("Cz")])
    np.testing.assert_allclose(mixed.centres[2], el.centres[UCL.index("TP9")])
    assert np.linalg.norm(mixed.centres[1] - xyz) < 0.5  # projected onto the polyhedron
    with pytest.raises(ValueError, match=r"positions\[1\]"):
        place_electrodes(mesh, ["Cz", (1.0, 2.0)], landmarks=LANDMARKS)


def test_register_positions_recovers_a_similarity(mesh):
    names, pos = layout_positions(mesh, UCL, landmarks=LANDMARKS)
    t = np.radians(25.0)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    rec = (pos @ rot.T + [10.0, -5.0, 3.0]) / 1000.0  # metres, in another frame
    reg = register_positions(mesh, rec, names=names, landmarks=LANDMARKS)
    # exact correspondences: the similarity is recovered to round-off
    np.testing.assert_allclose(reg.positions_mm, pos, atol=1e-6)
    assert abs(reg.scale - 1000.0) < 1e-6 and np.nanmax(reg.name_residual_mm) < 1e-6
    assert "scale 1000" in reg.report()
    # without names: closest points from centroid/radius alignment (frame roughly right)
    rot5 = np.array([[np.cos(0.05), -np.sin(0.05), 0], [np.sin(0.05), np.cos(0.05), 0], [0, 0, 1]])
    reg2 = register_positions(mesh, (pos @ rot5.T) / 1000.0)
    assert reg2.method == "icp" and np.median(reg2.scalp_distance_mm) < 1.0
    assert abs(reg2.scale / 1000.0 - 1) < 0.05


def test_landmark_file_and_report(mesh, tmp_path):
    (tmp_path / "f.json").write_text(
        '{"units": "m", "nz": [0, 0.096, 0], "iz": [0, -0.096, 0], "lpa": [-0.096, 0, 0], '
        '"rpa": [0.096, 0, 0]}')
    lm = load_landmarks(tmp_path / "f.json")
    np.testing.assert_allclose(lm["nasion"], [0, R, 0])
    (tmp_path / "f.csv").write_text("name,x,y,z\nnasion,0,96,0\ninion,0,-96,0\n"
                                    "lpa,-96,0,0\nrpa,96,0,0\n")
    lm2 = load_landmarks(tmp_path / "f.csv")
    for k in lm:
        np.testing.assert_allclose(lm2[k], lm[k])
    rep = landmark_report(mesh, lm)
    assert max(rep.values()) < 1.0  # the sphere's estimate is exact up to its faces
    (tmp_path / "bad.csv").write_text("name,x,y,z\nnasion,0,96\n")
    with pytest.raises(ValueError, match=r"bad.csv"):
        load_landmarks(tmp_path / "bad.csv")
