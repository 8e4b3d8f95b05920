"""The pipeline's stages: each reads what earlier stages wrote in the run folder and writes its own.

Each stage is ``fn(cfg, subject) -> summary dict``, with ``@stage(config=..., reads=...)`` beside it
naming the config sections and earlier stage folders it reads (its resume fingerprint). Stages only
wire configs to public library calls: every number they use is a config field or a library default.
"""

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from .. import io
from ..electrodes import (
    electrodes_from_config,
    is_electrode_name,
    place_electrodes,
    refined_mesh_config,
    register_positions,
)
from ..fem import Direct, build_forward_model, potentials, simulate
from ..fem.solvers import BlockCG
from ..geometry.layers import make_layers_reported
from ..geometry.quality import quality_report
from ..geometry.surface import extract_surfaces_reported
from ..geometry.tetrahedralize import tetrahedralize_reported
from ..inverse import (
    TSVD,
    Tikhonov,
    add_noise,
    grid_to_tets,
    image_metrics,
    jacobian_grid,
    make_grid,
    noise_std,
    reconstruct,
    spherical_perturbation,
)
from ..inverse.approx_error import approximation_error, sample_conductivities
from ..inverse.fit import LineSearchGaussNewton, fit_conductivities, fit_spectrum
from .._files import atomic_write_path
from ..phantom import make_head
from ..plot import plot_image_cut, plot_mesh_cut, plot_overlay, plot_scalp_potential
from ..protocol import Protocol, load_voltages, protocol_from_config, save_voltages
from ..segmentation import dice_scores, segment_reported
from ..segmentation.atlas import ATLAS_VERSION
from ..tissue import TISSUES, Tissue, sigma_per_tet
from .config import RunConfig
from .declare import stage
from .subject import Subject

logger = logging.getLogger(__name__)


@stage(config=("input",))
def run_input(cfg: RunConfig, subject: Subject) -> dict:
    """Make the phantom (or load the scan), write scan.nii.gz (+ labels) and an overlay PNG."""

    out = subject.dir("input")
    c = cfg.input
    if c.source == "mesh":
        return _input_mesh(cfg, out)
    labels = None
    if c.source == "phantom":

        kw = {} if c.noise is None else {"noise": c.noise}
        volume, labels = make_head(subject.modality, voxel_mm=c.voxel_mm, seed=c.seed, **kw)
    else:
        volume = io.load_volume(c.path)
        if c.labels_path:
            labels = io.load_labels(c.labels_path)
        if c.voxel_mm is not None:
            volume = io.resample(volume, c.voxel_mm)
            if labels is not None:
                labels = io.resample(labels, c.voxel_mm)
    io.save_volume(volume, out / "scan.nii.gz")
    if labels is not None:
        io.save_labels(labels, out / "labels.nii.gz")
    plot_overlay(volume, labels, out / "overlay.png",
                 title=f"{subject.name}: {subject.modality.upper()} scan" + (" and labels" if labels is not None else ""))
    return {"shape": list(volume.shape), "voxel_mm": volume.voxel_mm.tolist(),
            "has_labels": labels is not None}


def _input_mesh(cfg: RunConfig, out: Path) -> dict:
    """[input] source = "mesh": read the mesh made elsewhere, write it as input/mesh.vtu with a
    report (tissues, volumes, facing) and a cut-away PNG."""
    c = cfg.input
    mesh = io.load_mesh(c.mesh_path, reorient=c.reorient_tets, tissue_map=c.mesh_tissue_map(),
                        units=c.mesh_units, facing=c.facing)
    io.save_mesh(mesh, out / "mesh.vtu")
    vol = mesh.tet_volumes()
    facing = io.head_facing(mesh.nodes, mesh.tets)
    tissues = {t.name.lower(): {"tets": int((mesh.labels == int(t)).sum()),
                                "volume_ml": float(vol[mesh.labels == int(t)].sum() / 1000.0)}
               for t in TISSUES}
    lines = [f"mesh from {c.mesh_path} (made elsewhere: the segment, layers and surfaces stages "
             "are skipped and the mesh stage takes this mesh as it is)",
             f"{mesh.n_tets} tets, {mesh.n_nodes} nodes; tissue map: "
             f"{c.tissue_map if c.tissue_map is not None else 'the file own names / labels 1..4'}",
             f"facing: anterior {facing['anterior'] or 'undetermined (no neck offset from the cranium)'} "
             f"(facing = {c.facing!r}; after loading; +y is RAS)"]
    lines += [f"  {k:<6} {v['tets']:>9d} tets {v['volume_ml']:>10.1f} ml" for k, v in tissues.items()]
    _write_text(out / "report.txt", "\n".join(lines) + "\n")
    plot_mesh_cut(mesh, out / "mesh_cut.png", title=f"{Path(c.mesh_path).name}: {mesh.n_tets} tets")
    return {"mesh_path": c.mesh_path, "n_tets": mesh.n_tets, "n_nodes": mesh.n_nodes,
            "tissues": tissues, "anterior": facing["anterior"]}


def _skipped(cfg: RunConfig, subject: Subject, name: str) -> dict | None:
    """A stage that makes the mesh from a scan, in a run that starts from a mesh: skipped,
    with skipped.txt (shown on the report page) saying why."""
    if cfg.input.source != "mesh":
        return None
    why = (f"skipped: the run starts from the mesh [input] mesh_path = {cfg.input.mesh_path!r}, "
           f"so there is no scan to {name}")
    _write_text(subject.dir(name) / "skipped.txt", why + "\n")
    logger.info("%s", why)
    return {"skipped": why}


@stage(config=("segment",), reads=("input",), versions={"atlas": ATLAS_VERSION})
def run_segment(cfg: RunConfig, subject: Subject) -> dict:
    """Atlas registration + EM/MRF segmentation into brain, CSF, skull, scalp (and Dice vs truth)."""
    if (skip := _skipped(cfg, subject, "segment")) is not None:
        return skip
    volume = io.load_volume(subject.file("input", "scan.nii.gz"))
    seg_cfg = dataclasses.replace(cfg.segment, modality=subject.modality)
    labels, seg = segment_reported(volume, None, seg_cfg)
    out = subject.dir("segment")
    io.save_labels(labels, out / "labels.nii.gz")
    plot_overlay(volume, labels, out / "segmentation.png",
                 title=f"{subject.name}: {subject.modality.upper()} segmentation ({seg.atlas_name} atlas)")
    summary = {"atlas": seg.atlas_name, "registration": seg.registration,
               "voxels": {t.name.lower(): int((labels.labels == int(t)).sum()) for t in TISSUES}}
    truth_path = subject.file("input", "labels.nii.gz")
    if truth_path.exists():
        dice = dice_scores(labels, io.load_labels(truth_path))  # a truth on another grid is an error
        summary["dice_vs_truth"] = dice
        _write_text(out / "dice.txt", f"atlas  {seg.atlas_name}\n"
                    + "".join(f"{k:<6} {v:.4f}\n" for k, v in dice.items()))
    return summary


def _layer_sources(cfg: RunConfig) -> tuple[str, ...]:
    """The folders the layers stage reads: the input's, and the segmentation's if it runs."""
    return ("input", "segment") if cfg.stages is None or "segment" in cfg.stages else ("input",)


def _labels_for_layers(cfg: RunConfig, subject: Subject):
    """The label map the layers stage starts from: the segmentation if it ran, else the input's."""

    for source in _layer_sources(cfg)[::-1]:
        path = subject.file(source, "labels.nii.gz")
        if path.exists():
            return io.load_labels(path), source
    raise ValueError(
        f"[{subject.name}] no label map to build layers from: add the 'segment' stage, or give "
        "[input] labels_path (phantoms always have labels)."
    )


def _write_text(path, text: str) -> None:


    with atomic_write_path(path) as tmp:
        Path(tmp).write_text(text)


@stage(config=("layers",), reads=lambda cfg: _layer_sources(cfg))
def run_layers(cfg: RunConfig, subject: Subject) -> dict:
    """Hard labels -> nested layers (closing, nesting, minimum thickness), with a per-rule report."""
    if (skip := _skipped(cfg, subject, "layers")) is not None:
        return skip
    labels, source = _labels_for_layers(cfg, subject)
    layers, report = make_layers_reported(labels, cfg.layers)
    out = subject.dir("layers")
    io.save_labels(layers, out / "layers.nii.gz")
    _write_text(out / "report.txt", str(report))
    scan = io.load_volume(subject.file("input", "scan.nii.gz"))
    if scan.shape == layers.shape:
        plot_overlay(scan, layers, out / "layers.png", title=f"{subject.name}: layers")
    return {"from": source, **report.to_dict()}


@stage(config=("surfaces",), reads=("layers",))
def run_surfaces(cfg: RunConfig, subject: Subject) -> dict:
    """Layers -> four nested watertight surfaces (marching cubes, repair, Taubin, remeshing)."""
    if (skip := _skipped(cfg, subject, "surfaces")) is not None:
        return skip
    layers = io.load_labels(subject.file("layers", "layers.nii.gz"))
    surfaces, report = extract_surfaces_reported(layers, cfg.surfaces)
    out = subject.dir("surfaces")
    for tissue, surf in surfaces.items():
        io.save_surface(surf, out / f"{tissue.name.lower()}.stl")
    _write_text(out / "report.txt", str(report))
    return report.to_dict()


def _mesh_sources(cfg: RunConfig) -> tuple[str, ...]:
    """The mesh stage reads the surfaces, or the input's mesh in a run from a mesh file."""
    return ("input",) if cfg.input.source == "mesh" else ("surfaces",)


@stage(config=("mesh", "electrodes"), reads=_mesh_sources)  # refined under the electrodes
def run_mesh(cfg: RunConfig, subject: Subject) -> dict:
    """Surfaces -> labelled four-tissue tet mesh (fTetWild + improvement), with a cut-away PNG.

    In a run from a mesh file ([input] source = "mesh") it takes the input stage's mesh as it
    is (no meshing, no refinement under the electrodes) and says so in report.txt."""
    if cfg.input.source == "mesh":
        mesh = io.load_mesh(subject.file("input", "mesh.vtu"), facing="ignore")
        out = subject.dir("mesh")
        io.save_mesh(mesh, out / "mesh.vtu")
        _write_text(out / "report.txt", f"not meshed here: the mesh of [input] mesh_path = "
                    f"{cfg.input.mesh_path!r} as the input stage read it ({mesh.n_tets} tets, "
                    f"{mesh.n_nodes} nodes); [mesh] settings do not apply\n")
        return {"from": cfg.input.mesh_path, "n_tets": mesh.n_tets, "n_nodes": mesh.n_nodes}
    surfaces = {t: io.load_surface(subject.file("surfaces", f"{t.name.lower()}.stl"), t)
                for t in TISSUES}
    mesh_cfg = _mesh_config(cfg, surfaces)
    try:
        mesh, report = tetrahedralize_reported(surfaces, mesh_cfg)
    except RuntimeError as e:  # the mesher's own failure on these surfaces: an input problem
        raise ValueError(
            f"the mesher failed on {subject.root / 'surfaces'}/*.stl: {e} Check the surfaces "
            "stage's report.txt, or change [mesh] edge_mm / [surfaces] settings.") from e
    out = subject.dir("mesh")
    io.save_mesh(mesh, out / "mesh.vtu")
    _write_text(out / "report.txt", str(report))
    plot_mesh_cut(mesh, out / "mesh_cut.png",
                  title=f"{subject.name}: {mesh.n_tets} tets, {mesh.n_nodes} nodes")
    return report.to_dict()


def _mesh_config(cfg: RunConfig, surfaces):
    """The mesh stage's MeshConfig: [mesh], refined under the [electrodes] unless told not to."""


    mesh_cfg = cfg.mesh
    out = refined_mesh_config(mesh_cfg, surfaces[Tissue.SCALP], cfg.electrodes)
    if out is not mesh_cfg:
        logger.info("mesh: refining to %.1f mm within %.1f mm of %d electrode positions",
                    out.refine_edge_mm, out.refine_radius_mm, len(out.refine_points_mm))
    return out


@stage(config=("export",), reads=("mesh",))
def run_export(cfg: RunConfig, subject: Subject) -> dict:
    """Write the mesh as .msh (Gmsh), .vtu (ParaView) and .mat (MATLAB/EIDORS), as configured."""

    mesh = io.load_mesh(subject.file("mesh", "mesh.vtu"))
    out = subject.dir("export")
    written = [str(io.save_mesh(mesh, out / f"mesh.{ext}").name) for ext in cfg.export.formats]
    return {"files": written}


@stage(config=(), reads=("mesh",))
def run_quality(cfg: RunConfig, subject: Subject) -> dict:
    """The seed paper's Table-2 row and per-tissue quality statistics, with histograms."""


    mesh = io.load_mesh(subject.file("mesh", "mesh.vtu"))
    out = subject.dir("quality")
    report = quality_report(mesh, png_dir=out)
    # name the histograms relative to this folder: `out` is a staging folder renamed on success
    report = dataclasses.replace(report, png_paths=tuple(Path(p).name for p in report.png_paths))
    _write_text(out / "table2.txt", report.table())
    _write_text(out / "report.json", json.dumps(report.to_dict(), indent=2))
    return {"table2": report.table2_row}


@stage(config=("forward", "electrodes", "protocol"), reads=("mesh",))
def run_forward(cfg: RunConfig, subject: Subject) -> dict:
    """Electrodes on the scalp, a protocol, boundary voltages (CSV) and the scalp potential (PNG)."""


    mesh, electrodes, protocol, model = _forward_model(cfg, subject)
    sigma = cfg.forward.sigma()
    volts = np.asarray(simulate(model, sigma, protocol))
    out = subject.dir("forward")
    rows = np.asarray(protocol.rows)
    save_voltages(out / "voltages.csv", protocol, volts)  # 1-based, as protocol.csv
    cen = np.asarray(electrodes.centres)
    _write_text(out / "electrodes.csv", "name,x_mm,y_mm,z_mm\n" + "".join(
        f"{n},{c[0]:.3f},{c[1]:.3f},{c[2]:.3f}\n" for n, c in zip(electrodes.names, cen)))
    protocol.to_csv(out / "protocol.csv")
    inj = np.asarray(protocol.injections)
    k = cfg.forward.plot_injection
    if not 0 <= k < inj.shape[0]:
        raise ValueError(f"[forward] `plot_injection` = {k}, but the protocol has {inj.shape[0]} "
                         f"injections; use 0..{inj.shape[0] - 1}.")
    u, _ = potentials(model, sigma, inj[k:k + 1], current_a=protocol.current_a)
    faces, _ = mesh.boundary_faces()
    plot_scalp_potential(mesh.nodes, faces, np.asarray(u[0]), out / "scalp_potential.png",
                         electrodes_mm=cen,
                         title=f"{subject.name}: injection {electrodes.names[inj[k, 0]]} -> "
                               f"{electrodes.names[inj[k, 1]]}, {protocol.current_a * 1e6:.0f} uA")
    return {"n_elec": electrodes.n_elec, "n_rows": int(rows.shape[0]),
            "volts_min": float(volts.min()), "volts_max": float(volts.max())}


def _forward_model(cfg: RunConfig, subject: Subject):
    """The mesh, electrodes, protocol and forward model of a subject, as configured."""

    mesh = io.load_mesh(subject.file("mesh", "mesh.vtu"))
    electrodes = electrodes_from_config(mesh, cfg.electrodes)
    protocol = protocol_from_config(electrodes.n_elec, cfg.protocol)
    model = build_forward_model(mesh, electrodes, solver=_solver(cfg.forward.solver))
    return mesh, electrodes, protocol, model


@stage(config=("inverse", "forward", "electrodes", "protocol"), reads=("mesh",))
def run_inverse(cfg: RunConfig, subject: Subject) -> dict:
    """Reconstruct a simulated brain perturbation (TSVD/Tikhonov) and fit tissue conductivities.

    The Jacobian is summed straight into the reconstruction grid's brain cells tile by tile
    (`jacobian_grid`: no n_rows x n_tets matrix), the reconstruction is whitened by the noise
    level and column-normalised (tests/test_inverse_recovery.py), and the fit uses Gauss-Newton
    with a line search (`LineSearchGaussNewton`: about a third of Levenberg-Marquardt's forward
    solves). Simulated data come from the same mesh (no finer mesh exists in a pipeline run), so
    both results are optimistic about modelling error; see tests/test_inverse_recovery.py and
    the slow head tests for data from a different mesh.

    A recording (`[inverse] measured_path` read as "csv" or "ucl") is fitted with its own
    protocol and electrodes (`_fit_recording`); fit.txt, electrodes.csv, rejected.csv and, for
    several frequencies, spectrum.csv/png are written here.
    """
    c = cfg.inverse
    seconds: dict = {}
    summary: dict = {}
    out = subject.dir("inverse")
    recording = c.fit and c.measured_path is not None and c.measured_format != "voltages"
    if c.reconstruct or (c.fit and not recording):
        t0 = time.perf_counter()
        mesh, electrodes, protocol, model = _forward_model(cfg, subject)
        seconds["model"] = time.perf_counter() - t0
        v0 = None
        if c.reconstruct:
            v0 = _reconstruct(cfg, subject, mesh, model, protocol, out, summary, seconds)
        if c.fit and not recording:
            _fit_configured(cfg, electrodes, protocol, model, v0, out, summary, seconds)
    if recording:
        mesh = io.load_mesh(subject.file("mesh", "mesh.vtu"))
        _fit_recording(cfg, mesh, out, summary, seconds)
    summary["seconds"] = seconds
    return summary


def _reconstruct(cfg, subject, mesh, model, protocol, out, summary, seconds):
    """The simulated-perturbation reconstruction; returns the baseline voltages."""
    c = cfg.inverse
    sigma = cfg.forward.sigma()
    sigma_tet = sigma_per_tet(mesh, sigma)
    if c.centre_mm is None:
        brain = mesh.labels == int(Tissue.BRAIN)
        cen, vol = mesh.centroids()[brain], mesh.tet_volumes()[brain]
        middle = (cen * vol[:, None]).sum(0) / vol.sum()
        centre = middle + c.centre_height_fraction * np.array([0.0, 0.0, cen[:, 2].max() - middle[2]])
    else:
        centre = np.asarray(c.centre_mm, dtype=float)
    t0 = time.perf_counter()
    grid = make_grid(mesh, c.cell_mm, tissues=["brain"])
    Jg, v0 = jacobian_grid(model, sigma, protocol, grid, return_volts=True)
    seconds["jacobian_grid"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pert = spherical_perturbation(mesh, sigma_tet, centre, c.radius_mm, c.rel_change, tissue="brain")
    dv = np.asarray(simulate(model, pert, protocol)) - v0
    # Noise on each channel, relative to the baseline voltage (the seed paper's model).
    dv_noisy = add_noise(dv, c.noise_percent, seed=c.seed, reference=v0)
    seconds["simulate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    kind = TSVD if c.method == "tsvd" else Tikhonov
    if c.noise_percent > 0:
        # Whitened by the noise level, floored and NOSER-normalised as [inverse] says
        # (reconstruct_noise_floor, noser_exponent; their sources are in InverseConfig).
        std = noise_std(v0, c.noise_percent, floor=c.reconstruct_noise_floor)
        rec = reconstruct(Jg, dv_noisy, kind(noise_weighted=True, normalise=c.noser_exponent),
                          noise_std=std)
    else:
        rec = reconstruct(Jg, dv_noisy, kind(normalise=c.noser_exponent))
    x = np.asarray(rec.image)
    m = image_metrics(x, grid.centres, grid.volumes, centre, c.radius_mm,
                      sign=1 if c.rel_change > 0 else -1)
    seconds["reconstruct"] = time.perf_counter() - t0
    plot_image_cut(mesh, grid_to_tets(x, grid), out / "reconstruction.png", centre_mm=centre,
                   radius_mm=c.radius_mm, label="conductivity change (S/m)",
                   title=f"{subject.name}: {c.method.upper()} ({rec.rule}, k={rec.k:.0f}), "
                         f"{c.noise_percent}% noise; localisation error "
                         f"{m.localisation_error_mm:.1f} mm")
    summary.update({"centre_mm": centre.tolist(), "method": c.method, "rule": rec.rule,
                    "k": rec.k, "localisation_error_mm": m.localisation_error_mm,
                    "diameter_mm": m.diameter_mm, "volume_ratio": m.volume_ratio,
                    "n_cells": grid.n_cells})
    return v0


def _fit_configured(cfg, electrodes, protocol, model, v0, out, summary, seconds):
    """The fit on the configured electrodes and protocol: to noisy simulated voltages, or to
    `measured_path` read as "voltages" (`load_voltages`, the configured protocol's order)."""
    c = cfg.inverse
    sigma = cfg.forward.sigma()
    t0 = time.perf_counter()
    if v0 is None:
        v0 = np.asarray(simulate(model, sigma, protocol))
    if c.measured_path is None:  # noisy simulated voltages at the [forward] conductivities
        measured = add_noise(v0, c.noise_percent, seed=c.seed + 1)
        reference = v0
    else:
        measured = load_voltages(c.measured_path, protocol)
        reference = measured
    fit_std = (noise_std(reference, c.noise_percent, floor=c.noise_floor)
               if c.noise_percent > 0 else None)
    src = (f"`measured_path` {c.measured_path!r}" if c.measured_path is not None
           else "the simulated voltages")
    _check_noise(c, fit_std, reference, protocol, src)
    ae = None
    if c.approx_error_mesh is not None:
        ae = _approx_error(cfg, electrodes, model, protocol, sigma)
        summary["approx_error_rel"] = float(np.linalg.norm(ae.mean) / np.linalg.norm(v0))
        seconds["approx_error"] = time.perf_counter() - t0
    opts, notes = c.fit_keywords(protocol, recording=False)
    res = fit_conductivities(model, protocol, measured, init=np.asarray(c.fit_init_s_m),
                             noise_std=fit_std, approx_error=ae,
                             solver=LineSearchGaussNewton(rtol=c.fit_rtol, atol=c.fit_atol),
                             max_steps=c.fit_max_steps, throw=False, **opts)
    if c.measured_path is not None:
        _check_finite(c, res, "")
    if ae is not None:
        table = (f"approximation-error model against {c.approx_error_mesh} "
                 f"({c.approx_error_draws} draws; mean error "
                 f"{100 * summary['approx_error_rel']:.2f} % of the voltages)\n\n")
    else:
        table = ""
    if c.measured_path is None:
        table += (res.table(sigma) + "\n\ndata: simulated at the [forward] conductivities, "
                  f"{c.noise_percent} % noise\n")
        summary["fit_rel_error"] = (res.sigma / sigma - 1).tolist()
    else:
        table += res.table() + f"\n\ndata: {c.measured_path}\n"
    table += "".join(f"{n}\n" for n in notes)
    _write_text(out / "fit.txt", table)
    summary.update(_fit_summary(res))
    seconds["fit"] = time.perf_counter() - t0


def _check_noise(c, fit_std, reference, protocol, src, at=""):
    """A channel whose noise model is 0 would be trusted infinitely: an error naming it."""
    if fit_std is not None and np.any(fit_std <= 0):
        i = int(np.flatnonzero(fit_std <= 0)[0])
        raise ValueError(
            f"[inverse] {src}{at}: the voltage of protocol row {i} (electrodes "
            f"{(np.asarray(protocol.rows)[i] + 1).tolist()}, 1-based) is {reference[i]} V, "
            f"so its noise ({c.noise_percent} % of it, noise_floor = {c.noise_floor}) is 0 "
            f"and the fit would trust it infinitely ({int((fit_std <= 0).sum())} such rows); "
            "set [inverse] noise_floor > 0 (e.g. 0.1) or remove the channel.")


def _check_finite(c, res, at):
    if not np.all(np.isfinite(res.std_error)):
        raise ValueError(
            f"[inverse] the fit to `measured_path` {c.measured_path!r}{at} has no finite standard "
            f"errors (sigma {res.sigma.tolist()}, std errors {res.std_error.tolist()}): the "
            "data do not determine the conductivities. Check that the rows follow the "
            "protocol (forward/protocol.csv); a one-column file cannot be checked, the "
            "five-column format (source, sink, meas+, meas-, volts) can.")


def _fit_summary(res) -> dict:
    return {"fit_sigma": res.sigma.tolist(), "fit_std_error": res.std_error.tolist(),
            "fit_estimates": {n: [float(e), float(se)] for n, e, se in
                              zip(res.fitted, res.estimates, res.std_error)},
            "fit_rejected_rows": res.rejected.tolist(),
            "fit_n_forward": res.n_forward, "fit_n_steps": res.n_steps,
            "fit_converged": res.success}


def _recording_electrodes(cfg: RunConfig, mesh, m):
    """The recording's electrodes on the head: by name, by registered position or as the
    [electrodes] layout (`[inverse] measured_electrodes`). Returns (electrodes, mode, note)."""
    c, e = cfg.inverse, cfg.electrodes
    names = list(m.electrode_names)
    mode = c.measured_electrodes
    if mode == "auto":
        mode = ("names" if names and all(map(is_electrode_name, names))
                else "positions" if m.positions_mm is not None else "config")
    landmarks = None if e.landmarks_mm is None else dict(e.landmarks_mm)
    kw = dict(radius_mm=e.radius_mm, contact_impedance_ohm_m2=e.contact_impedance_ohm_m2,
              max_distance_mm=e.max_distance_mm)
    where = f"[inverse] measured_electrodes = {mode!r}"
    if mode == "names":
        if not names:
            raise ValueError(f"{where}, but {m.source} names no electrodes; use "
                             "measured_electrodes = \"positions\" or \"config\".")
        unknown = [n for n in names if not is_electrode_name(n)]
        if unknown:
            raise ValueError(
                f"{where}: {m.source} has electrode names {unknown} that are not 10-10 / 10-5 "
                "names (jaxhead.electrodes.TEN_TEN, EXTENDED); rename them in the file, or set "
                "measured_electrodes = \"positions\" to register the file's coordinates.")
        el = place_electrodes(mesh, names, landmarks=landmarks, **kw)
        note = (f"electrodes: {len(names)} placed by name, landmarks "
                + ("from [electrodes] landmarks_mm" if landmarks else
                   "estimated from the scalp (RAS assumed; give [electrodes] landmarks_mm on a "
                   "real head)"))
        return el, mode, note
    if mode == "positions":
        if m.positions_mm is None:
            raise ValueError(f"{where}, but {m.source} gives no electrode positions; use "
                             "measured_electrodes = \"names\" or \"config\".")
        reg = register_positions(mesh, m.positions_mm, names=names or None, landmarks=landmarks,
                                 max_distance_mm=e.max_distance_mm)
        el = place_electrodes(mesh, reg.positions_mm, names=names or None, **kw)
        return el, mode, "electrodes: the file's positions, " + reg.report()
    el = electrodes_from_config(mesh, e)
    if el.n_elec != m.n_elec:
        raise ValueError(
            f"{where}: the [electrodes] layout places {el.n_elec} electrodes but {m.source} has "
            f"{m.n_elec}; set [electrodes] layout to its {m.n_elec} electrodes (a count or their "
            "names), or measured_electrodes = \"names\" / \"positions\".")
    return el, mode, f"electrodes: the [electrodes] layout {e.layout!r}"


def _fit_recording(cfg: RunConfig, mesh, out: Path, summary: dict, seconds: dict) -> None:
    """Fit a recording ("csv"/"ucl"): its protocol, electrodes, one or several frequencies."""
    c = cfg.inverse
    t0 = time.perf_counter()
    m = io.load_measurements(c.measured_path, format=c.measured_format,
                             voltages_path=c.measured_voltages_path,
                             current_a=c.measured_current_a, variable=c.measured_variable)
    freqs = np.asarray(m.frequencies_hz)
    if c.frequency_hz is None:
        if freqs.size != 1:
            raise ValueError(
                f"[inverse] {m.source} has {freqs.size} frequencies "
                f"({', '.join(f'{f:g}' for f in freqs)} Hz) and `frequency_hz` is not set; set "
                "frequency_hz = one of them, a list, or \"all\".")
        cols = [0]
    elif c.frequency_hz == "all":
        cols = list(range(freqs.size))
    else:
        want = c.frequency_hz if isinstance(c.frequency_hz, tuple) else (c.frequency_hz,)
        try:
            cols = [m.frequency_index(f) for f in want]
        except ValueError as err:
            raise ValueError(f"[inverse] `frequency_hz` = {c.frequency_hz!r}: {err} Set "
                             "frequency_hz to one of them or \"all\".") from None
    electrodes, mode, el_note = _recording_electrodes(cfg, mesh, m)
    protocol = Protocol(m.rows, m.current_a)
    model = build_forward_model(mesh, electrodes, solver=_solver(cfg.forward.solver))
    seconds["model"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    opts, notes = c.fit_keywords(protocol, recording=True)
    if c.approx_error_mesh is not None:
        opts["approx_error"] = _approx_error(cfg, electrodes, model, protocol, cfg.forward.sigma())
        notes.append(f"approximation-error model against {c.approx_error_mesh} "
                     f"({c.approx_error_draws} draws)")
        seconds["approx_error"] = time.perf_counter() - t0
    src = f"`measured_path` {c.measured_path!r}"
    for k in cols:
        at = "" if np.isnan(freqs[k]) else f" at {freqs[k]:g} Hz"
        std = (noise_std(m.voltages[k], c.noise_percent, floor=c.noise_floor)
               if c.noise_percent > 0 else None)
        _check_noise(c, std, m.voltages[k], protocol, src, at)
    spec = fit_spectrum(model, m, init=np.asarray(c.fit_init_s_m),
                        frequencies_hz=None if len(cols) == freqs.size and cols == list(
                            range(freqs.size)) else freqs[cols],
                        noise_percent=c.noise_percent if c.noise_percent > 0 else None,
                        noise_floor=c.noise_floor,
                        solver=LineSearchGaussNewton(rtol=c.fit_rtol, atol=c.fit_atol),
                        max_steps=c.fit_max_steps, throw=False, **opts)
    for f, res in zip(spec.frequencies_hz, spec.results):
        _check_finite(c, res, "" if np.isnan(f) else f" at {f:g} Hz")
    names = electrodes.names
    lines, rejected = [], []
    for f, res in zip(spec.frequencies_hz, spec.results):
        lines += [("frequency: unknown (one voltage column)" if np.isnan(f)
                   else f"frequency {f:g} Hz"), res.table(), ""]
        for r in res.rejected.tolist():
            rejected.append((f, r + 1, *(names[i] for i in m.rows[r])))
    lines += [f"data: {m.source} ({m.n_rows} rows, {m.n_elec} electrodes, current "
              f"{m.current_a:g} A, {len(cols)} of {freqs.size} frequencies)", el_note, *notes]
    if rejected:
        lines.append(f"rejected channels: {len(rejected)} (rejected.csv)")
    _write_text(out / "fit.txt", "\n".join(lines) + "\n")
    cen = np.asarray(electrodes.centres)
    _write_text(out / "electrodes.csv", "name,x_mm,y_mm,z_mm\n" + "".join(
        f"{n},{p[0]:.3f},{p[1]:.3f},{p[2]:.3f}\n" for n, p in zip(names, cen)))
    _write_text(out / "rejected.csv", "frequency_hz,row,source,sink,meas_plus,meas_minus\n"
                + "".join(f"{f:g},{r},{a},{b},{p},{q}\n" for f, r, a, b, p, q in rejected))
    if len(spec.results) > 1:
        with atomic_write_path(out / "spectrum.csv") as tmp:
            spec.to_csv(tmp)
        spec.plot(out / "spectrum.png")
    first = spec.results[0]
    summary.update(_fit_summary(first) if len(spec.results) == 1 else {
        "fit_sigma": [r.sigma.tolist() for r in spec.results],
        "fit_std_error": [r.std_error.tolist() for r in spec.results],
        "fit_n_forward": sum(r.n_forward for r in spec.results),
        "fit_n_steps": sum(r.n_steps for r in spec.results),
        "fit_converged": all(r.success for r in spec.results)})
    summary.update({
        "fit_data": str(m.source), "fit_frequencies_hz": [None if np.isnan(f) else float(f)
                                                          for f in spec.frequencies_hz],
        "fit_electrodes": mode, "fit_gain": [r.gain for r in spec.results],
        "fit_rejected": [int(r.rejected.size) for r in spec.results],
        "fit_options": json.loads(json.dumps({k: v for k, v in opts.items()
                                              if k != "approx_error"}))})
    seconds["fit"] = time.perf_counter() - t0


def _approx_error(cfg: RunConfig, electrodes, model, protocol, sigma):
    """The approximation-error model of a run's mesh against `[inverse] approx_error_mesh`."""

    fine = io.load_mesh(cfg.inverse.approx_error_mesh)
    fine_el = place_electrodes(fine, electrodes.centres, radius_mm=cfg.electrodes.radius_mm,
                               contact_impedance_ohm_m2=cfg.electrodes.contact_impedance_ohm_m2,
                               names=list(electrodes.names),
                               max_distance_mm=cfg.electrodes.max_distance_mm)
    accurate = build_forward_model(fine, fine_el, solver=_solver(cfg.forward.solver))
    draws = sample_conductivities(cfg.inverse.approx_error_draws, centre=sigma,
                                  seed=cfg.inverse.seed + 2)
    return approximation_error(accurate, model, draws, protocol)


def _solver(name: str):

    if name == "direct":
        return Direct()

    return BlockCG()


#: Stage name -> function, in pipeline order.
STAGES = {
    "input": run_input,
    "segment": run_segment,
    "layers": run_layers,
    "surfaces": run_surfaces,
    "mesh": run_mesh,
    "export": run_export,
    "quality": run_quality,
    "forward": run_forward,
    "inverse": run_inverse,
}
