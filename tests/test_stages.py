"""The forward and inverse pipeline stages on a ready-made mesh (a 4-shell sphere)."""

import dataclasses
import json

import numpy as np
import pytest

from jaxhead import save_mesh
from jaxhead.run.config import (ElectrodeConfig, ForwardConfig, InputConfig, InverseConfig,
                            RunConfig)
from jaxhead.run import StageError
from jaxhead.run.pipeline import run_pipeline
from jaxhead.protocol import ProtocolConfig
from sphere_mesh import structured_sphere_mesh


def test_forward_and_inverse_stages(tmp_path):
    mesh = structured_sphere_mesh(h_mm=20.0)
    (tmp_path / "run/mri/mesh").mkdir(parents=True)
    save_mesh(mesh, tmp_path / "run/mri/mesh/mesh.vtu")
    cfg = RunConfig(
        out_dir=str(tmp_path / "run"), stages=("forward", "inverse"),
        input=InputConfig(modalities=("mri",)),
        electrodes=ElectrodeConfig(layout=16, radius_mm=8.0),
        protocol=ProtocolConfig(kind="opposite"),
        forward=ForwardConfig(sigma_s_m={"skull": 0.02}),
        inverse=InverseConfig(centre_mm=(0.0, 20.0, 30.0), radius_mm=20.0, cell_mm=15.0,
                              fit=True),
    )
    res = run_pipeline(cfg, progress=lambda s: None)
    out = tmp_path / "run/mri"
    rows = np.loadtxt(out / "forward/voltages.csv", delimiter=",", skiprows=2)  # comment, header
    assert rows.shape == (res["mri"]["forward"]["n_rows"], 5)
    # The forward stage used the configured skull conductivity, the defaults elsewhere.
    from jaxhead.electrodes import place_electrodes, spread_positions
    from jaxhead.fem import build_forward_model, simulate
    from jaxhead.protocol import opposite

    el = place_electrodes(mesh, spread_positions(mesh, 16), radius_mm=8.0)
    v = simulate(build_forward_model(mesh, el), np.array([0.3, 1.79, 0.02, 0.44]), opposite(16))
    np.testing.assert_allclose(rows[:, 4], np.asarray(v), rtol=1e-6)
    assert (out / "forward/scalp_potential.png").stat().st_size > 10_000
    inv = json.loads((out / "inverse/done.json").read_text())["summary"]
    # Reconstruction quality is tested in test_inverse_recovery.py; here: the stage ran and
    # measured a blob inside the head (radius 96 mm).
    assert 0 <= inv["localisation_error_mm"] < 96 and inv["n_cells"] > 10, inv
    assert (out / "inverse/reconstruction.png").exists()
    # The fit ran to convergence (its accuracy: tests/test_fit.py) and reported its cost.
    assert (out / "inverse/fit.txt").exists() and inv["fit_n_forward"] >= 2, inv
    assert np.all(np.isfinite(inv["fit_rel_error"])) and set(inv["seconds"]) >= {
        "jacobian_grid", "reconstruct", "fit"}, inv


def test_inverse_stage_fits_measured_voltages(tmp_path):
    # Voltages written by the forward stage (skull 0.02 S/m) come back as "measured" data: the
    # fit recovers the conductivities that made them, and a changed file reruns the stage.
    mesh = structured_sphere_mesh(h_mm=20.0)
    (tmp_path / "run/mri/mesh").mkdir(parents=True)
    save_mesh(mesh, tmp_path / "run/mri/mesh/mesh.vtu")
    common = dict(out_dir=str(tmp_path / "run"), input=InputConfig(modalities=("mri",)),
                  electrodes=ElectrodeConfig(layout=16, radius_mm=8.0),
                  protocol=ProtocolConfig(kind="opposite"),
                  forward=ForwardConfig(sigma_s_m={"skull": 0.02}))
    run_pipeline(RunConfig(stages=("forward",), **common), progress=lambda s: None)
    measured = tmp_path / "measured.csv"
    measured.write_text((tmp_path / "run/mri/forward/voltages.csv").read_text())
    cfg = RunConfig(stages=("forward", "inverse"), **common,
                    inverse=InverseConfig(cell_mm=15.0, measured_path=str(measured)))
    inv = run_pipeline(cfg, progress=lambda s: None)["mri"]["inverse"]
    np.testing.assert_allclose(inv["fit_sigma"], [0.3, 1.79, 0.02, 0.44], rtol=1e-3)
    assert "fit_rel_error" not in inv  # no truth for measured data
    assert str(measured) in (tmp_path / "run/mri/inverse/fit.txt").read_text()
    # Same file: up to date. Edited file (other voltages): the inverse stage runs again.
    lines = []
    assert run_pipeline(cfg, progress=lines.append)
    assert any("inverse: up to date" in s for s in lines), lines
    from jaxhead.protocol import load_voltages, opposite, save_voltages

    p = opposite(16)
    save_voltages(measured, p, 1.05 * load_voltages(measured, p))
    lines = []
    inv2 = run_pipeline(cfg, progress=lines.append)["mri"]["inverse"]
    assert any("inverse: running" in s for s in lines) and inv2["fit_sigma"] != inv["fit_sigma"]
    # Issue 14: a one-column file in reversed order was fitted (NaN standard errors, exit 0).
    volts = load_voltages(measured, p)
    one_col = tmp_path / "one_column.csv"
    one_col.write_text("volts\n" + "".join(f"{v!r}\n" for v in volts[::-1]))
    bad = dataclasses.replace(cfg, inverse=InverseConfig(cell_mm=15.0, measured_path=str(one_col)))
    with pytest.raises(StageError, match="one_column.csv.*protocol"):
        run_pipeline(bad, progress=lambda s: None, report=False)
    # Issue 14: a zero voltage ended a fit after a minute naming neither file nor line.
    zero = volts.copy()
    zero[3] = 0.0
    save_voltages(measured, p, zero)
    with pytest.raises(StageError, match=r"measured.csv.*protocol row 3 .*is 0.0 V.*noise_floor"):
        run_pipeline(cfg, progress=lambda s: None, report=False)
    with pytest.raises(ValueError, match="measured_path"):
        InverseConfig(measured_path=str(tmp_path / "missing.csv"))
    with pytest.raises(ValueError, match="noise_floor"):
        InverseConfig(noise_floor=-0.1)
    with pytest.raises(ValueError, match="approx_error_draws"):
        InverseConfig(approx_error_draws=1)


def test_inverse_stage_fit_with_the_approximation_error(tmp_path):
    # Measured voltages from a finer mesh (9 mm grid) at skull 0.02 S/m, fitted on the run's
    # 18 mm mesh: the approximation-error model against the finer mesh, configured by path,
    # takes the fit from a biased one to the truth (tests/test_approx_error.py has the algebra).
    from jaxhead.electrodes import place_electrodes, spread_positions
    from jaxhead.fem import build_forward_model, simulate
    from jaxhead.protocol import opposite, save_voltages

    coarse, fine = structured_sphere_mesh(h_mm=18.0), structured_sphere_mesh(h_mm=9.0)
    (tmp_path / "run/mri/mesh").mkdir(parents=True)
    save_mesh(coarse, tmp_path / "run/mri/mesh/mesh.vtu")
    save_mesh(fine, tmp_path / "fine.vtu")
    truth = np.array([0.3, 1.79, 0.02, 0.44])
    el = place_electrodes(fine, spread_positions(coarse, 16), radius_mm=10.0)
    p = opposite(16)
    save_voltages(tmp_path / "measured.csv", p,
                  np.asarray(simulate(build_forward_model(fine, el), truth, p)))
    def cfg(ae_mesh):
        return RunConfig(
            out_dir=str(tmp_path / "run"), stages=("inverse",),
            input=InputConfig(modalities=("mri",)),
            electrodes=ElectrodeConfig(layout=16, radius_mm=10.0),
            protocol=ProtocolConfig(kind="opposite"),
            inverse=InverseConfig(cell_mm=15.0, measured_path=str(tmp_path / "measured.csv"),
                                  measured_format="voltages",  # the plain fit, as configured
                                  approx_error_mesh=ae_mesh))

    # Without the error model the fit runs away (brain 200 S/m, NaN standard errors): an error
    # naming the file, not a result (it was written as one, exit 0, before issue 14).
    with pytest.raises(StageError, match="measured.csv.*no finite standard errors"):
        run_pipeline(cfg(None), progress=lambda s: None, report=False)
    corrected = run_pipeline(cfg(str(tmp_path / "fine.vtu")), progress=lambda s: None,
                             report=False)["mri"]["inverse"]
    err = np.abs(np.asarray(corrected["fit_sigma"]) / truth - 1)
    print("with the error model", err)
    assert corrected["approx_error_rel"] > 0.01 and "approx_error" in corrected["seconds"]
    assert np.all(err < 0.03), err  # measured: 0.3 / 0.8 / 0.04 / 0.03 %
    assert "approximation-error model" in (tmp_path / "run/mri/inverse/fit.txt").read_text()


# --- Issue 15: recordings and meshes made elsewhere, through the run API -------------------------

REC_NAMES = ["Fp1", "Fp2", "F7", "F8", "T7", "T8", "O1", "O2", "Cz", "NFpz"]


def _ucl_recording(tmp_path, mesh, *, freqs=(10.0, 100.0), bad_rows=(7,)):
    """A UCL-layout recording written here: 10 named electrodes (NFpz the reference), per-
    electrode contact impedances, a gain of 1.1, an offset per injection, 0.1 % noise and the
    rows `bad_rows` of the first frequency scaled by 1.2. Brain differs between frequencies."""
    from jaxhead.electrodes import place_electrodes
    from jaxhead.fem import build_forward_model, simulate
    from jaxhead.protocol import reference_protocol
    from test_measurements import write_mat73

    rng = np.random.default_rng(3)
    el = place_electrodes(mesh, REC_NAMES, radius_mm=8.0)
    model = build_forward_model(mesh, el)
    n = len(REC_NAMES)
    prot = reference_protocol(n, n - 1, [(i, (i + 4) % 9) for i in range(9)],
                              include_injecting=True, current_a=1e-4)
    z = 0.02 * np.exp(rng.normal(0.0, 0.3, n))
    truths, volts = [], []
    for k, _ in enumerate(freqs):
        truth = np.array([0.3 * (1 + 0.1 * k), 1.79, 0.02, 0.44])
        v = 1.1 * np.asarray(simulate(model, truth, prot, contact_impedance_ohm_m2=z))
        v = v + rng.normal(0, 1e-3, prot.n_inj)[prot.drive_index]
        v = v * (1 + 1e-3 * rng.standard_normal(v.shape))
        if k == 0:
            v[list(bad_rows)] *= 1.2
        truths.append(truth)
        volts.append(v)
    settings = {"Freq": list(freqs), "Protocol": (prot.rows + 1).tolist(),
                "ElectrodePosition": (np.asarray(el.centres) / 1000.0).tolist(),
                "ElectrodeNames": REC_NAMES, "CurrentA": prot.current_a}
    (tmp_path / "rec.json").write_text(json.dumps(settings))
    write_mat73(tmp_path / "rec.mat", {"BV": np.asarray(volts).T * 1e3})  # (n_rows, n_freq) mV
    return tmp_path / "rec.json", prot, np.asarray(truths)


def _mesh_run(tmp_path, mesh, **inverse):
    (tmp_path / "run/mri/mesh").mkdir(parents=True, exist_ok=True)
    save_mesh(mesh, tmp_path / "run/mri/mesh/mesh.vtu")
    return RunConfig(out_dir=str(tmp_path / "run"), stages=("inverse",),
                     input=InputConfig(modalities=("mri",)),
                     electrodes=ElectrodeConfig(layout=16, radius_mm=8.0),
                     inverse=InverseConfig(reconstruct=False, **inverse))


def test_inverse_stage_fits_a_ucl_recording(tmp_path):
    # Deliver 6: the recording brings its protocol, current, frequencies and electrode names;
    # the measured-data defaults (gain, offset per injection, per-electrode contact impedances,
    # Cauchy loss, 5-SD rejection) recover both frequencies' conductivities. On this coarse
    # sphere the CSF shell is one tet thick: CSF is fixed at its truth (with it free, brain and
    # CSF traded off, 16 % and 37 % off) and a scalp prior anchors the scale the gain leaves
    # open (the default CSF prior cannot when CSF is invisible: all else came out 9-13 % high).
    mesh = structured_sphere_mesh(h_mm=16.0)
    rec, prot, truths = _ucl_recording(tmp_path, mesh, bad_rows=())
    fixed_csf = dict(fit_tissues=("brain", "skull", "scalp"), fit_init_s_m=(0.2, 1.79, 0.03, 0.3),
                     fit_priors={"scalp": (0.44, 0.01)}, fit_max_steps=100)
    cfg = _mesh_run(tmp_path, mesh, measured_path=str(rec), frequency_hz="all",
                    noise_percent=0.1, **fixed_csf)
    assert cfg.inverse.measured_format == "ucl"
    assert cfg.inverse.measured_voltages_path == str(tmp_path / "rec.mat")  # fingerprinted
    inv = run_pipeline(cfg, progress=lambda s: None, report=False)["mri"]["inverse"]
    err = np.abs(np.asarray(inv["fit_sigma"]) / truths - 1)
    print(err)
    assert np.all(err < 0.02) and inv["fit_converged"], err
    assert inv["fit_electrodes"] == "names" and inv["fit_frequencies_hz"] == [10.0, 100.0]
    opts = inv["fit_options"]
    assert opts["gain"] and opts["offsets"] == "per_injection" and opts["loss"] == "cauchy"
    assert opts["contact_impedance"] == "per_electrode" and opts["priors"] == {"scalp": [0.44, 0.01]}
    np.testing.assert_allclose(inv["fit_gain"], 1.1, rtol=0.02)
    out = tmp_path / "run/mri/inverse"
    # clean data: nothing rejected (a corrupted row: test_a_corrupted_row_in_a_small_montage)
    assert (out / "rejected.csv").read_text().splitlines() == [
        "frequency_hz,row,source,sink,meas_plus,meas_minus"]
    assert inv["fit_rejected"] == [0, 0]
    text = (out / "fit.txt").read_text()
    assert "prior added" not in text and "never carry current" in text and "NFpz" in (
        out / "electrodes.csv").read_text()
    spec = np.loadtxt(out / "spectrum.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(spec[:, 0], [10.0, 100.0])
    assert (out / "spectrum.png").stat().st_size > 5_000
    # The implicit voltages file is part of the fingerprint: an edited .mat reruns the stage.
    lines = []
    run_pipeline(cfg, progress=lines.append, report=False)
    assert any("inverse: up to date" in s for s in lines), lines
    from test_measurements import write_mat73

    import scipy.io  # noqa: F401  (the .mat is v7.3: h5py)
    import h5py

    with h5py.File(tmp_path / "rec.mat", "r") as f:
        bv = np.asarray(f["BV"]).T
    write_mat73(tmp_path / "rec.mat", {"BV": bv * 1.01})
    by_name = np.loadtxt(out / "electrodes.csv", delimiter=",", skiprows=1, usecols=(1, 2, 3))
    lines = []
    # one frequency; the file's coordinates (metres, its own frame) registered to the scalp
    cfg2 = _mesh_run(tmp_path, mesh, measured_path=str(rec), frequency_hz=100.0,
                     noise_percent=0.1, measured_electrodes="positions", **fixed_csf)
    inv2 = run_pipeline(cfg2, progress=lines.append, report=False)["mri"]["inverse"]
    assert any("inverse: running" in s for s in lines), lines
    assert inv2["fit_frequencies_hz"] == [100.0] and not (out / "spectrum.csv").exists()
    assert inv2["fit_electrodes"] == "positions" and "registration (names)" in (
        out / "fit.txt").read_text()
    registered = np.loadtxt(out / "electrodes.csv", delimiter=",", skiprows=1, usecols=(1, 2, 3))
    assert np.abs(registered - by_name).max() < 0.5  # the file holds the by-name centres, in m
    # volts x 1.01: the gain. Registered discs differ from the data's by up to 0.5 mm on 16 mm
    # faces: measured skull +2.7 %, the rest within 2 %.
    np.testing.assert_allclose(inv2["fit_sigma"], truths[1], rtol=0.05)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known defect (issue 15, session 6): the free offsets are "
                   "profiled by least squares, so with 9 rows per injection one row x 1.2 biases "
                   "its injection's offset and 6 clean rows of that injection are rejected with it "
                   "(rows 2-4, 6-9 at 10 Hz); the realistic case, 32 rows per injection, is not hit")
def test_a_corrupted_row_in_a_small_montage(tmp_path):
    mesh = structured_sphere_mesh(h_mm=16.0)
    rec, prot, truths = _ucl_recording(tmp_path, mesh, bad_rows=(7,))
    cfg = _mesh_run(tmp_path, mesh, measured_path=str(rec), frequency_hz="all",
                    noise_percent=0.1, fit_tissues=("brain", "skull", "scalp"),
                    fit_init_s_m=(0.2, 1.79, 0.03, 0.3), fit_priors={"scalp": (0.44, 0.01)},
                    fit_max_steps=100)
    inv = run_pipeline(cfg, progress=lambda s: None, report=False)["mri"]["inverse"]
    assert inv["fit_rejected"] == [1, 0]  # row 8 (1-based) at 10 Hz only


def test_fit_options_defaults_for_recordings_and_simulated_data():
    from jaxhead.protocol import adjacent, reference_protocol
    from jaxhead.inverse.fit import CSF_PRIOR

    def fit_options(c, protocol, recording):
        return c.fit_keywords(protocol, recording=recording)

    ref = reference_protocol(6, 5, [(0, 1), (2, 3)], include_injecting=True)
    kw, notes = fit_options(InverseConfig(), ref, recording=True)
    assert kw["gain"] and kw["offsets"] == "per_injection" and kw["loss"] == "cauchy"
    assert kw["contact_impedance"] == "per_electrode" and kw["contact_prior"] == 2.0
    assert kw["priors"] == {"csf": CSF_PRIOR} and kw["reject_sigma"] == 5.0
    assert any("prior added: csf" in n for n in notes)
    # electrodes 5 and 6 (1-based) never carry current: their impedances are the prior's
    assert any("electrodes [5, 6] (1-based) never carry current" in n for n in notes)
    # UCL's own protocol leaves the injecting electrodes out: one common factor
    kw, notes = fit_options(InverseConfig(), reference_protocol(6, 5, [(0, 1), (2, 3)]),
                            recording=True)
    assert kw["contact_impedance"] == "common" and kw["contact_prior"] is None
    # a differential protocol has no reference electrode: no offsets
    kw, _ = fit_options(InverseConfig(), adjacent(8), recording=True)
    assert kw["offsets"] is None
    # simulated data: the plain fit, as before issue 15
    kw, notes = fit_options(InverseConfig(), ref, recording=False)
    assert kw == dict(fit=("brain", "csf", "skull", "scalp"), gain=False, offsets=None,
                      contact_impedance=False, contact_prior=None, priors=None, loss="linear",
                      loss_scale=3.0, reject_sigma=None)
    # a fixed tissue anchors the gain's scale: no prior added; 0 turns rejection off
    kw, notes = fit_options(InverseConfig(fit_tissues=("brain", "skull", "scalp"),
                                          fit_reject_sigma=0.0), ref, recording=True)
    assert kw["priors"] is None and kw["reject_sigma"] is None
    assert not any("prior added" in n for n in notes)


def test_inverse_stage_recording_errors(tmp_path):
    mesh = structured_sphere_mesh(h_mm=16.0)
    rec, prot, _ = _ucl_recording(tmp_path, mesh)
    run = lambda **kw: run_pipeline(_mesh_run(tmp_path, mesh, measured_path=str(rec), **kw),  # noqa: E731
                                    progress=lambda s: None, report=False)
    with pytest.raises(StageError, match=r"rec.json has 2 frequencies \(10, 100 Hz\).*frequency_hz"):
        run()
    with pytest.raises(StageError, match=r"`frequency_hz` = 50.0.*not in the file.*10, 100"):
        run(frequency_hz=50.0)
    # names unknown to the 10-10 system: an error naming them and the fix
    settings = json.loads(rec.read_text())
    settings["ElectrodeNames"] = ["E1"] + REC_NAMES[1:]
    rec.write_text(json.dumps(settings))
    with pytest.raises(StageError, match=r"\['E1'\].*measured_electrodes = \"positions\""):
        run(frequency_hz=10.0, measured_electrodes="names")
    # ... and the config layout with another electrode count
    with pytest.raises(StageError, match=r"places 16 electrodes but .*rec.json has 10"):
        run(frequency_hz=10.0, measured_electrodes="config")


def _simnibs_msh(mesh, path):
    """The mesh as SimNIBS writes one: volume tags 2 (grey matter), 3 (CSF), 4 (bone), 5 (scalp),
    no physical names."""
    import meshio

    tags = np.array([0, 2, 3, 4, 5])[mesh.labels].astype(np.int32)
    meshio.write(path, meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)],
                                   cell_data={"gmsh:physical": [tags], "gmsh:geometrical": [tags]}),
                 file_format="gmsh22", binary=False)


def test_run_from_a_simnibs_and_an_eidors_mesh(tmp_path):
    # Deliver 5: [input] source = "mesh" starts a run from a mesh made elsewhere; the stages that
    # make a mesh from a scan are skipped with a note, the mesh stage takes the file's mesh, and
    # the forward voltages are those of the same mesh built here.
    import scipy.io

    mesh = structured_sphere_mesh(h_mm=20.0)
    _simnibs_msh(mesh, tmp_path / "head.msh")
    common = dict(electrodes=ElectrodeConfig(layout=16, radius_mm=8.0),
                  protocol=ProtocolConfig(kind="opposite"))
    cfg = RunConfig(out_dir=str(tmp_path / "run"),
                    stages=("input", "segment", "layers", "surfaces", "mesh", "forward"),
                    input=InputConfig(source="mesh", mesh_path=str(tmp_path / "head.msh"),
                                      tissue_map="simnibs"), **common)
    res = run_pipeline(cfg, progress=lambda s: None, report=False)["subject"]
    out = tmp_path / "run/subject"
    for name in ("segment", "layers", "surfaces"):
        assert "skipped" in res[name] and "head.msh" in (out / name / "skipped.txt").read_text()
    from jaxhead import load_mesh

    got = load_mesh(out / "mesh/mesh.vtu")
    np.testing.assert_array_equal(got.labels, mesh.labels)
    np.testing.assert_allclose(got.nodes, mesh.nodes)
    assert "not meshed here" in (out / "mesh/report.txt").read_text()
    report = (out / "input/report.txt").read_text()
    assert "tissue map: simnibs" in report and "skull" in report, report
    v_msh = np.loadtxt(out / "forward/voltages.csv", delimiter=",", skiprows=2)[:, 4]
    # The same mesh as an EIDORS contributed model: vtx in metres, 1-based tri, materials.
    names = np.empty((1, 4), dtype=object)
    names[0, :] = ["grey matter", "CSF", "bone", "skin"]
    scipy.io.savemat(tmp_path / "head.mat", {
        "vtx": mesh.nodes / 1000.0, "tri": (mesh.tets + 1).astype(float),
        "materials": {"ref": mesh.labels.astype(float)[:, None], "names": names}})
    cfg = RunConfig(out_dir=str(tmp_path / "run2"), stages=("input", "mesh", "forward"),
                    input=InputConfig(source="mesh", mesh_path=str(tmp_path / "head.mat"),
                                      mesh_units="m"), **common)
    run_pipeline(cfg, progress=lambda s: None, report=False)
    v_mat = np.loadtxt(tmp_path / "run2/subject/forward/voltages.csv", delimiter=",",
                       skiprows=2)[:, 4]
    np.testing.assert_allclose(v_mat, v_msh, rtol=1e-9)
    # the input stage's fingerprint covers the mesh file: an edited file reruns it
    lines = []
    run_pipeline(cfg, progress=lines.append, report=False)
    assert sum("up to date" in s for s in lines) == 3, lines
    scipy.io.savemat(tmp_path / "head.mat", {
        "vtx": mesh.nodes / 1000.0 * 1.01, "tri": (mesh.tets + 1).astype(float),
        "materials": {"ref": mesh.labels.astype(float)[:, None], "names": names}})
    lines = []
    run_pipeline(cfg, progress=lines.append, report=False)
    assert sum("running" in s for s in lines) == 3, lines
    # unmapped tissues: an error naming the labels and the fix
    with pytest.raises(StageError, match=r"volume tags \[2, 3, 4, 5\].*tissue_map"):
        run_pipeline(dataclasses.replace(cfg, out_dir=str(tmp_path / "run3"), input=InputConfig(
            source="mesh", mesh_path=str(tmp_path / "head.msh"))), progress=lambda s: None,
            report=False)
