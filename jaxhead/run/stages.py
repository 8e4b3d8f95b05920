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
from ..electrodes import electrode_positions, electrodes_from_config, place_electrodes
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
from ..inverse.fit import LineSearchGaussNewton, fit_conductivities
from .._files import atomic_write_path
from ..phantom import make_head
from ..plot import plot_image_cut, plot_mesh_cut, plot_overlay, plot_scalp_potential
from ..protocol import load_voltages, protocol_from_config, save_voltages
from ..segmentation import dice_scores, segment_reported
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


@stage(config=("segment",), reads=("input",))
def run_segment(cfg: RunConfig, subject: Subject) -> dict:
    """Atlas registration + EM/MRF segmentation into brain, CSF, skull, scalp (and Dice vs truth)."""
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

    layers = io.load_labels(subject.file("layers", "layers.nii.gz"))
    surfaces, report = extract_surfaces_reported(layers, cfg.surfaces)
    out = subject.dir("surfaces")
    for tissue, surf in surfaces.items():
        io.save_surface(surf, out / f"{tissue.name.lower()}.stl")
    _write_text(out / "report.txt", str(report))
    return report.to_dict()


@stage(config=("mesh", "electrodes"), reads=("surfaces",))  # refined under the electrodes
def run_mesh(cfg: RunConfig, subject: Subject) -> dict:
    """Surfaces -> labelled four-tissue tet mesh (fTetWild + improvement), with a cut-away PNG."""

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
    if not cfg.electrodes.refine_mesh or mesh_cfg.refine_points_mm:
        return mesh_cfg  # refinement off, or the user's own refine points
    pos = electrode_positions(surfaces[Tissue.SCALP], cfg.electrodes)
    # The rule `ElectrodeConfig.refine_mesh` documents (with its measured effect): at least the
    # electrode radius plus two refined edges.
    radius = max(mesh_cfg.refine_radius_mm, cfg.electrodes.radius_mm + 2 * mesh_cfg.refine_edge_mm)
    logger.info("mesh: refining to %.1f mm within %.1f mm of %d electrode positions",
                mesh_cfg.refine_edge_mm, radius, len(pos))
    return dataclasses.replace(mesh_cfg, refine_points_mm=tuple(map(tuple, pos.tolist())),
                               refine_radius_mm=radius)


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
    solves). Data come from the same mesh (no finer mesh exists in a pipeline run), so both
    results are optimistic about modelling error; see tests/test_inverse_recovery.py and the
    slow head tests for data from a different mesh.
    """



    c = cfg.inverse
    seconds = {}
    t0 = time.perf_counter()
    mesh, electrodes, protocol, model = _forward_model(cfg, subject)
    sigma = cfg.forward.sigma()
    sigma_tet = sigma_per_tet(mesh, sigma)
    if c.centre_mm is None:
        brain = mesh.labels == int(Tissue.BRAIN)
        cen, vol = mesh.centroids()[brain], mesh.tet_volumes()[brain]
        middle = (cen * vol[:, None]).sum(0) / vol.sum()
        centre = middle + c.centre_height_fraction * np.array([0.0, 0.0, cen[:, 2].max() - middle[2]])
    else:
        centre = np.asarray(c.centre_mm, dtype=float)
    seconds["model"] = time.perf_counter() - t0
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
        std = None
        rec = reconstruct(Jg, dv_noisy, kind(normalise=c.noser_exponent))
    x = np.asarray(rec.image)
    m = image_metrics(x, grid.centres, grid.volumes, centre, c.radius_mm,
                      sign=1 if c.rel_change > 0 else -1)
    seconds["reconstruct"] = time.perf_counter() - t0
    out = subject.dir("inverse")
    plot_image_cut(mesh, grid_to_tets(x, grid), out / "reconstruction.png", centre_mm=centre,
                   radius_mm=c.radius_mm, label="conductivity change (S/m)",
                   title=f"{subject.name}: {c.method.upper()} ({rec.rule}, k={rec.k:.0f}), "
                         f"{c.noise_percent}% noise; localisation error "
                         f"{m.localisation_error_mm:.1f} mm")
    summary = {"centre_mm": centre.tolist(), "method": c.method, "rule": rec.rule, "k": rec.k,
               "localisation_error_mm": m.localisation_error_mm, "diameter_mm": m.diameter_mm,
               "volume_ratio": m.volume_ratio, "n_cells": grid.n_cells}
    if c.fit:
        t0 = time.perf_counter()
        if c.measured_path is None:  # noisy simulated voltages at the [forward] conductivities
            measured = add_noise(v0, c.noise_percent, seed=c.seed + 1)
            reference = v0
        else:
            measured = load_voltages(c.measured_path, protocol)
            reference = measured
        fit_std = (noise_std(reference, c.noise_percent, floor=c.noise_floor)
                   if c.noise_percent > 0 else None)
        if fit_std is not None and np.any(fit_std <= 0):
            i = int(np.flatnonzero(fit_std <= 0)[0])
            src = (f"`measured_path` {c.measured_path!r}" if c.measured_path is not None
                   else "the simulated voltages")
            raise ValueError(
                f"[inverse] {src}: the voltage of protocol row {i} (electrodes "
                f"{(np.asarray(protocol.rows)[i] + 1).tolist()}, 1-based) is {reference[i]} V, "
                f"so its noise ({c.noise_percent} % of it, noise_floor = {c.noise_floor}) is 0 "
                f"and the fit would trust it infinitely ({int((fit_std <= 0).sum())} such rows); "
                "set [inverse] noise_floor > 0 (e.g. 0.1) or remove the channel.")
        ae = None
        if c.approx_error_mesh is not None:
            ae = _approx_error(cfg, electrodes, model, protocol, sigma)
            summary["approx_error_rel"] = float(np.linalg.norm(ae.mean) / np.linalg.norm(v0))
            seconds["approx_error"] = time.perf_counter() - t0
        res = fit_conductivities(model, protocol, measured, init=np.asarray(c.fit_init_s_m),
                                 noise_std=fit_std, approx_error=ae,
                                 solver=LineSearchGaussNewton(rtol=c.fit_rtol, atol=c.fit_atol),
                                 max_steps=c.fit_max_steps, throw=False)
        if c.measured_path is not None and not np.all(np.isfinite(res.std_error)):
            raise ValueError(
                f"[inverse] the fit to `measured_path` {c.measured_path!r} has no finite standard "
                f"errors (sigma {res.sigma.tolist()}, std errors {res.std_error.tolist()}): the "
                "data do not determine the conductivities. Check that the rows follow the "
                "protocol (forward/protocol.csv); a one-column file cannot be checked, the "
                "five-column format (source, sink, meas+, meas-, volts) can.")
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
        _write_text(out / "fit.txt", table)
        summary["fit_sigma"] = res.sigma.tolist()
        summary["fit_std_error"] = res.std_error.tolist()
        summary["fit_n_forward"] = res.n_forward
        summary["fit_n_steps"] = res.n_steps
        summary["fit_converged"] = res.success
        seconds["fit"] = time.perf_counter() - t0
    summary["seconds"] = seconds
    return summary


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
