"""The study engine: samples as Dask tasks, results written atomically per sample.  [host]

`run_study(config)` validates everything (config, scheduler) before any work; builds the
reference head once (a task: phantom or label map -> layers -> surfaces -> tetrahedralize ->
electrodes, saved to `<out_dir>/study/reference/`); computes the first-order counterpart of
every grf perturbation (a task); then runs every sample as a task that takes plain data (a dict,
paths, a seed) and writes `<out_dir>/study/samples/<id>.json` atomically. A rerun skips samples
whose file exists (failed ones too, unless `retry_failed`), so a killed study finishes only the
missing samples. Failures are recorded with their error and never stop the study.

Workers (STYLE.md, "Parallel and cluster runs"): an embedded `distributed.LocalCluster` of
single-threaded processes (spawned by Dask's nanny: JAX is never forked after it starts; BLAS at
one thread; XLA_PYTHON_CLIENT_PREALLOCATE=false when processes share a GPU), or an existing
scheduler by address (`dask scheduler`, or dask-jobqueue's `SLURMCluster(...).scheduler_address`
for a cluster). Each worker process builds the reference's forward model and measures once and
keeps them (a per-process cache keyed by the reference folder).
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
import traceback
from pathlib import Path

import meshio
import numpy as np
from distributed import Client, LocalCluster, as_completed
from tqdm import tqdm

from ..electrodes import Electrodes, place_electrodes
from ..fem import build_forward_model, simulate
from ..geometry import TetMesh, extract_surfaces, make_layers, tetrahedralize
from ..io import atomic_write_path, load_labels, load_mesh, load_volume, resample, write_csv
from ..phantom import make_head
from ..protocol import adjacent, opposite
from ..segmentation import config_atlas, dice_scores, segment
from ..tissue import TISSUE_NAMES, Tissue
from ..volume import LabelMap, Volume
from .config import ReferenceConfig, StudyConfig, load_study_config, segment_config
from .first_order import (
    displacement_sensitivity,
    first_order_summary,
    fit_map,
    node_gradients,
    taylor_terms,
)
from .grf import sample_grf
from .measures import (
    MEASURE_COLUMNS,
    MeasureConfig,
    Reference,
    blob_data,
    blob_sigma,
    measure,
)
from .morph import MorphError, build_morph, morph_nodes, morph_quality
from .perturb import jitter_electrodes, perturb_labels
from .resegmentation import resegment

logger = logging.getLogger(__name__)

#: samples.csv columns, in order (the issue's list, then the route's diagnostics).
COLUMNS = ("sample", "perturbation", "tissue", "amplitude", "seed", "route", *MEASURE_COLUMNS,
           "seconds", "error", "correlation_mm", "n_inverted", "min_scaled_jacobian",
           "rel_voltage_change_first_order", "linearisation_error", "description",
           "first_order_rel_error", "second_order_rel_error",
           "dice_brain", "dice_csf", "dice_skull", "dice_scalp", "bias_percent", "settings")
#: The Dice columns: a re-mesh sample's label map against the reference label map, per tissue.
DICE_COLUMNS = tuple(f"dice_{t}" for t in TISSUE_NAMES)

#: The first-order vs sampled agreement (issue 13's bar), as summary.json states it.
AGREEMENT_MEASURE = ("per sample e = ||dV - S d|| / ||dV||: dV = V(morphed head) - V(reference) "
                     "the sampled change, S d the first-order change (S = dV/dd through the "
                     "morph at d = 0), Euclidean norms over all protocol rows; the bar holds when "
                     "every sample's e is below it")
SECOND_ORDER_MEASURE = ("per sample ||dV - (S d + 1/2 D2V[dx, dx])|| / ||dV||: the same sampled dV "
                        "against the second-order prediction (dx = x(d) - x0 the morph's node "
                        "displacement, linear in d; D2V by forward-over-forward AD at x0)")
DISTRIBUTION_MEASURE = ("what the first-order route predicts for a study: the RMS over samples of "
                        "rel_voltage_change, sqrt(trace S C S^T) / ||V||, against the sampled RMS "
                        "of n samples (ratio sampled / first order; ratio_sampling_sd = "
                        "sqrt(1 / (2 n dof)), dof = trace(S C S^T)^2 / trace((S C S^T)^2), is the "
                        "ratio's expected Monte Carlo scatter)")
AGREEMENT_BAR = 0.10
AGREEMENT_MAX_SD_MM = 0.5

_WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
               "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}


# ----------------------------------------------------------------------------------------------
# The reference head (a task)


def _protocol(rc):
    return (adjacent if rc["protocol"] == "adjacent" else opposite)(rc["n_elec"],
                                                                    current_a=rc["current_a"])


def _x64():
    import jax  # the task is an entry point: float64 for the FEM (STYLE.md, Conventions 3)

    jax.config.update("jax_enable_x64", True)


def prepare_reference(cfg: dict, ref_dir: str) -> str:
    """Build and save the reference head (task). Returns the path of reference.npz.

    With a segmented reference ([study.reference] segmented, or source = "scan") the label map is
    `segment` of the scan with the reference's SegmentConfig; reference/segmentation.json then
    gives the settings and, for a phantom, the Dice of that segmentation against the true labels.
    """
    _x64()
    path = Path(ref_dir) / "reference.npz"
    if path.is_file():
        return str(path)
    rc = cfg["reference"]
    rcfg = ReferenceConfig(**rc)
    scan = None
    if rc["source"] == "mesh":  # no label map: the re-mesh route is unavailable (checked up front)
        mesh = load_mesh(rc["mesh_path"])
        labels = LabelMap(np.zeros((1, 1, 1), np.uint8), np.eye(4))
    else:
        truth = None
        if rc["source"] == "phantom":
            scan, labels = truth = make_head(rc["modality"], voxel_mm=rc["voxel_mm"], seed=rc["seed"])
        elif rc["source"] == "scan":
            scan = load_volume(rc["scan_path"])
            if rc["voxel_mm"] is not None:
                scan = resample(scan, rc["voxel_mm"])
        else:
            labels = load_labels(rc["labels_path"])
            if rc["voxel_mm"] is not None:
                labels = resample(labels, rc["voxel_mm"])
        if rcfg.has_scan_labels:
            scfg = rcfg.segment_config()
            t0 = time.perf_counter()
            labels = segment(scan, config_atlas(scfg), scfg)
            info = {"segment": rc["segment"], "seconds": round(time.perf_counter() - t0, 3),
                    "voxels": {t: int((labels.labels == k + 1).sum())
                               for k, t in enumerate(TISSUE_NAMES)}}
            if truth is not None:
                info["dice_vs_phantom_truth"] = dice_scores(labels, truth[1])
            Path(ref_dir).mkdir(parents=True, exist_ok=True)
            with atomic_write_path(Path(ref_dir) / "segmentation.json") as tmp:
                tmp.write_text(json.dumps(info, indent=1))
        mesh = _mesh_of(labels)
    el = place_electrodes(mesh, rc["n_elec"], radius_mm=rc["electrode_radius_mm"],
                          contact_impedance_ohm_m2=rc["contact_impedance_ohm_m2"])
    Path(ref_dir).mkdir(parents=True, exist_ok=True)
    with atomic_write_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, nodes=mesh.nodes, tets=mesh.tets, labels=mesh.labels,
                     label_map=labels.labels, affine=labels.affine, centres=el.centres,
                     efaces=el.faces, face_electrode=el.face_electrode,
                     contact_impedance_ohm_m2=el.contact_impedance_ohm_m2, names=np.array(el.names),
                     face_areas=el.face_areas_mm2,
                     scan=np.asarray(scan.data) if scan is not None else np.zeros((0, 0, 0)))
    return str(path)


def _mesh_of(labels: LabelMap) -> TetMesh:
    """The library's own route from a label map to a mesh (the re-mesh route)."""
    return tetrahedralize(extract_surfaces(make_layers(labels)))


def load_reference(ref_path) -> tuple[LabelMap, TetMesh, Electrodes]:
    """The reference head that `prepare_reference` saved: (label map, mesh, electrodes).

    The label map is a 1-voxel placeholder when the reference came from a mesh file.
    """
    with np.load(ref_path) as d:
        labels = LabelMap(d["label_map"], d["affine"])
        mesh = TetMesh(d["nodes"], d["tets"], d["labels"])
        el = Electrodes(d["centres"], d["efaces"], d["face_electrode"], d["contact_impedance_ohm_m2"],
                        tuple(str(n) for n in d["names"]), d["face_areas"])
    return labels, mesh, el


def load_reference_scan(ref_path) -> Volume | None:
    """The reference's scan (phantom or scan file, on the label map's grid), or None (no scan)."""
    with np.load(ref_path) as d:
        scan = d["scan"] if "scan" in d else np.zeros((0, 0, 0))
        return Volume(scan, d["affine"]) if scan.size else None


class _Worker:
    """What a worker process keeps of one reference: mesh, model, measures, morph, sensitivity."""

    def __init__(self, cfg: dict, ref_path: str):
        rc = cfg["reference"]
        self.cfg = cfg
        self.label_map, self.mesh, self.electrodes = load_reference(ref_path)
        self.radius_mm = rc["electrode_radius_mm"]
        self.sigma = ReferenceConfig(**rc).sigma()
        self.protocol = _protocol(rc)
        self.model = build_forward_model(self.mesh, self.electrodes)
        mc = dict(cfg["measures"])
        if mc.get("blob_centre_mm") is not None:
            mc["blob_centre_mm"] = tuple(mc["blob_centre_mm"])
        self.ref = Reference(self.mesh, self.model, self.protocol, self.sigma, MeasureConfig(**mc))
        self._morph = None
        self._atlas = None
        self.ref_path = ref_path
        self.first_order_path = Path(ref_path).parent.parent / "first_order" / "sensitivity.npz"

    @property
    def morph(self):
        if self._morph is None:
            self._morph = build_morph(self.mesh, stiffening=self.cfg["reference"]["stiffening"])
        return self._morph

    @property
    def atlas(self):
        if self._atlas is None:
            self._atlas = config_atlas(ReferenceConfig(**self.cfg["reference"]).segment_config())
        return self._atlas

    def sensitivity(self, tissue: str):
        if not self.first_order_path.is_file():
            return None
        with np.load(self.first_order_path) as d:
            return d[f"S_{tissue}"] if f"S_{tissue}" in d else None


_CACHE: dict[str, _Worker] = {}


def _worker(cfg: dict, ref_path: str) -> _Worker:
    if ref_path not in _CACHE:
        _CACHE.clear()  # one reference per process at a time (memory)
        _CACHE[ref_path] = _Worker(cfg, ref_path)
    return _CACHE[ref_path]


# ----------------------------------------------------------------------------------------------
# Tasks


def run_first_order(cfg: dict, ref_path: str, out_dir: str) -> dict:
    """Sensitivity of the voltages to each grf interface's normal displacement (task).

    Writes first_order/sensitivity.npz (S per interface, V/mm), one .vtu and PNG map per
    interface, and returns the first-order predictions per grf perturbation.
    """
    _x64()
    w = _worker(cfg, ref_path)
    out = Path(out_dir) / "first_order"
    out.mkdir(parents=True, exist_ok=True)
    grfs = [p for p in cfg["perturbations"] if p["kind"] == "grf"]
    tissues = sorted({p["tissue"] for p in grfs}, key=TISSUE_NAMES.index)
    t0 = time.perf_counter()
    G = node_gradients(w.model, w.sigma, w.protocol)
    S = displacement_sensitivity(w.model, w.morph, w.sigma, w.protocol, tissues=tissues,
                                 node_grad=G)
    del G
    seconds = time.perf_counter() - t0
    arrays = {f"S_{Tissue(t).name.lower()}": s for t, s in S.items()}
    with atomic_write_path(out / "sensitivity.npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    A = fit_map(w.model, w.sigma, w.protocol, w.ref.noise_sd)
    maps = {}
    for t, s in S.items():
        name = Tissue(t).name.lower()
        surf = w.morph.interface(t)
        # noise units per mm of displacement per mm^2 of interface (a density, mesh-independent)
        density = np.linalg.norm(s / w.ref.noise_sd[:, None], axis=0) / surf.areas_mm2
        maps[name] = _write_map(out, name, surf.points(w.mesh.nodes), surf.faces, density)
    preds = []
    for p in grfs:
        surf = w.morph.interface(p["tissue"])
        fo = first_order_summary(S[Tissue.parse(p["tissue"])], surf.points(w.mesh.nodes),
                                 p["amplitude"], p["correlation_mm"], w.ref.volts,
                                 w.ref.noise_sd, A=A, sigma=w.sigma)
        preds.append({"tissue": p["tissue"], "amplitude": p["amplitude"],
                      "correlation_mm": p["correlation_mm"], **fo})
    return {"seconds": seconds, "predictions": preds, "maps": maps}


def _write_map(out: Path, name: str, points, faces, values) -> dict:
    """A sensitivity map on an interface: .vtu (point data) and a PNG (two views)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vtu = out / f"sensitivity_{name}.vtu"
    with atomic_write_path(vtu) as tmp:
        meshio.write(str(tmp), meshio.Mesh(points, [("triangle", faces)],
                                           point_data={"noise_units_per_mm_per_mm2": values}),
                     file_format="vtu")
    png = out / f"sensitivity_{name}.png"
    fig = plt.figure(figsize=(9, 4))
    for i, (elev, azim) in enumerate([(20, -60), (20, 120)]):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        tri = ax.plot_trisurf(points[:, 0], points[:, 1], points[:, 2], triangles=faces,
                              cmap="viridis", linewidth=0, antialiased=False)
        tri.set_array(values[faces].mean(1))
        ax.view_init(elev, azim)
        ax.set_axis_off()
    fig.colorbar(tri, ax=fig.axes, shrink=0.7, label="|dV / dn| / noise per mm^2 (1/mm^3)")
    fig.suptitle(f"sensitivity to the {name} interface's normal displacement")
    with atomic_write_path(png) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return {"vtu": vtu.name, "png": png.name, "max": float(values.max()),
            "median": float(np.median(values))}


def run_sample(sample: dict, cfg: dict, ref_path: str, out_dir: str) -> dict:
    """One perturbed head, measured (task). Writes samples/<id>.json and returns the row."""
    _x64()
    t0 = time.perf_counter()
    row = {c: "" for c in COLUMNS}
    row.update({k: sample.get(k, "") for k in ("sample", "perturbation", "tissue", "amplitude",
                                               "seed", "route", "correlation_mm", "bias_percent",
                                               "settings", "key")})
    extra = {}  # route diagnostics, kept when the sample fails (e.g. a morph's inverted tets)
    timings = {}  # seconds per step (samples/<id>.json only; benchmarks/study.py reads them)
    try:
        fresh = ref_path not in _CACHE
        w = _worker(cfg, ref_path)
        if fresh:
            timings["worker_setup"] = round(time.perf_counter() - t0, 3)
        row.update(_measure_sample(w, sample, extra, timings))
    except Exception as e:  # noqa: BLE001 (a failed sample is data, not a crash)
        row.update(extra)
        row["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:300]}"
        logger.info("sample %s failed:\n%s", sample["sample"], traceback.format_exc())
    row["seconds"] = round(time.perf_counter() - t0, 3)
    row["timings"] = timings
    path = Path(out_dir) / "samples" / f"{sample['sample']}.json"
    with atomic_write_path(path) as tmp:
        tmp.write_text(json.dumps(row, default=_json_default))
    return row


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(type(x).__name__)


def _measure_sample(w: _Worker, s: dict, extra: dict, timings: dict) -> dict:
    kind, route, seed = s["perturbation"], s["route"], int(s["seed"])
    t = time.perf_counter()

    def lap(name):
        nonlocal t
        now = time.perf_counter()
        timings[name] = round(now - t, 3)
        t = now

    cfg, sigma, prot = w.ref.cfg, w.sigma, w.protocol
    if route == "morph":
        surf = w.morph.interface(s["tissue"])
        d = sample_grf(surf.points(w.mesh.nodes), s["amplitude"], s["correlation_mm"],
                       seed=seed)[0]
        x = morph_nodes(w.morph, {s["tissue"]: d})
        q = morph_quality(w.morph, x, raise_on_inverted=False)
        extra.update({"n_inverted": q.n_inverted, "min_scaled_jacobian": q.min_scaled_jacobian,
                 "description": json.dumps({"kind": "grf", "tissue": s["tissue"],
                                            "sd_mm": s["amplitude"], "seed": seed,
                                            "correlation_mm": s["correlation_mm"],
                                            "max_displacement_mm": q.max_displacement_mm})})
        lap("perturb")
        if q.n_inverted:
            raise MorphError(f"the morph inverts {q.n_inverted} tets (max node displacement "
                             f"{q.max_displacement_mm:.2f} mm); lower the amplitude or use a "
                             "longer correlation length")
        v = np.asarray(simulate(w.model, sigma, prot, nodes=x))
        blob = blob_data(w.mesh, w.model, sigma, prot, w.ref.centre_mm, cfg, nodes=x) \
            if cfg.imaging else None
        S = w.sensitivity(Tissue.parse(s["tissue"]).name.lower())
        if S is not None:
            lin = S @ d
            dv = v - w.ref.volts
            extra["rel_voltage_change_first_order"] = float(np.linalg.norm(lin)
                                                            / np.linalg.norm(w.ref.volts))
            err1 = float(np.linalg.norm(dv - lin) / np.linalg.norm(dv))
            extra["linearisation_error"] = extra["first_order_rel_error"] = err1
            # second order: 1/2 D2V(x0)[dx, dx], dx the morph's (linear) node displacement
            t2 = time.perf_counter()
            _, d2 = taylor_terms(w.model, sigma, prot, np.asarray(x) - w.mesh.nodes)
            extra["second_order_rel_error"] = float(np.linalg.norm(dv - lin - 0.5 * d2)
                                                    / np.linalg.norm(dv))
            timings["second_order"] = round(time.perf_counter() - t2, 3)
            t += time.perf_counter() - t2  # the "forward" lap leaves it out
    elif route == "remesh":
        if kind == "resegment":
            labels, desc = _resegment(w, s, seed)
        else:
            labels, desc = perturb_labels(w.label_map, kind, tissue=s["tissue"] or None,
                                          amplitude=s["amplitude"], seed=seed)
            desc["dice"] = dice_scores(labels, w.label_map)
        extra.update({f"dice_{t}": desc["dice"][t] for t in TISSUE_NAMES})
        lap("perturb")
        mesh = _mesh_of(labels)
        lap("mesh")
        el = place_electrodes(mesh, w.electrodes.centres, radius_mm=w.radius_mm,
                              contact_impedance_ohm_m2=w.electrodes.contact_impedance_ohm_m2,
                              names=w.electrodes.names)
        model = build_forward_model(mesh, el)
        v = np.asarray(simulate(model, sigma, prot))
        blob = (np.asarray(simulate(model, blob_sigma(mesh, sigma, w.ref.centre_mm, cfg), prot))
                if cfg.imaging else None)
        desc.update(n_tets=mesh.n_tets, n_nodes=mesh.n_nodes)
        extra["description"] = json.dumps(desc)
    else:  # electrodes
        el, desc = jitter_electrodes(w.mesh, w.electrodes, s["amplitude"], seed=seed,
                                     radius_mm=w.radius_mm)
        model = build_forward_model(w.mesh, el)
        v = np.asarray(simulate(model, sigma, prot))
        blob = (np.asarray(simulate(model, blob_sigma(w.mesh, sigma, w.ref.centre_mm, cfg), prot))
                if cfg.imaging else None)
        extra["description"] = json.dumps(desc)
    lap("forward")
    m = measure(w.ref, v, blob)
    lap("measures")
    return {**m, **extra}


def _resegment(w: _Worker, s: dict, seed: int):
    """A resegment sample's labels: the reference scan, changed (seeded), segmented again."""
    scan = load_reference_scan(w.ref_path)
    if scan is None:  # guarded by StudyConfig; a reference saved without its scan lands here
        raise ValueError("the reference has no scan to re-segment (source = \"labels\" or \"mesh\")")
    settings = json.loads(s["settings"]) if s.get("settings") else {}
    base = ReferenceConfig(**w.cfg["reference"]).segment_config()
    scfg = segment_config(base.modality, settings, base=base, where="settings")
    labels, desc = resegment(scan, w.label_map, s["amplitude"], atlas=w.atlas, cfg=scfg,
                             bias_percent=float(s.get("bias_percent") or 0.0), seed=seed)
    desc["settings"] = settings
    return labels, desc


# ----------------------------------------------------------------------------------------------
# The driver


def expand_samples(cfg: StudyConfig) -> list[dict]:
    """Every sample of the study as plain data: id, perturbation, tissue, amplitude, seed, route."""
    out = []
    for j, p in enumerate(cfg.perturbations):
        seeds = np.random.SeedSequence([int(cfg.seed), j]).generate_state(p.samples)
        for k in range(p.samples):
            tissue = p.tissue or ""
            s = {"sample": f"{len(out):04d}-{p.kind}{'-' + tissue if tissue else ''}-{p.amplitude:g}-{k}",
                 "perturbation": p.kind, "tissue": tissue, "amplitude": float(p.amplitude),
                 "seed": int(seeds[k]), "route": p.realised_by,
                 "correlation_mm": float(p.correlation_mm) if p.kind == "grf" else "",
                 "key": cfg.sample_key(j, k, seeds[k])}
            if p.kind == "resegment":
                s["bias_percent"] = float(p.bias_percent)
                s["settings"] = json.dumps(p.settings, sort_keys=True) if p.settings else ""
            out.append(s)
    return out


def connect(workers: int | None = None, scheduler: str | None = None, *, timeout_s: float = 10.0):
    """A Dask client: an existing scheduler by address, else an embedded LocalCluster.

    Arguments:
        workers: embedded cluster size (default: the CPU count); one single-threaded process each.
        scheduler: address of a running scheduler ("tcp://host:8786"); `workers` is then unused.
        timeout_s: how long to try to reach the scheduler.

    Returns:
        (client, cluster or None): close both when done.
    """
    if scheduler is not None:
        try:
            return Client(scheduler, timeout=f"{timeout_s}s"), None
        except (OSError, TimeoutError, ValueError) as e:
            raise ValueError(
                f"cannot reach the Dask scheduler at {scheduler!r} ({type(e).__name__}: {e}); "
                "start one with `dask scheduler` (or a dask-jobqueue cluster) and pass its "
                "address, or drop --scheduler to use an embedded cluster.") from None
    n = (os.cpu_count() or 1) if workers is None else int(workers)
    if n < 1:
        raise ValueError(f"`workers` = {workers}; use at least 1 (or None for one per core).")
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           dashboard_address=None, env=_WORKER_ENV, silence_logs=logging.ERROR)
    return Client(cluster), cluster


def run_study(config, *, workers: int | None = None, scheduler: str | None = None,
              progress: bool | None = None) -> Path:
    """Run a segmentation-error study; returns `<out_dir>/study`.

    Arguments:
        config: a StudyConfig or the path of a TOML file with a [study] section.
        workers: processes of the embedded LocalCluster (default one per core).
        scheduler: address of an existing Dask scheduler instead of the embedded cluster.
        progress: show a progress bar (default: when stderr is a terminal).

    Returns:
        The study folder with samples.csv, summary.json, samples/*.json, first_order/, figures.
    """
    cfg = config if isinstance(config, StudyConfig) else load_study_config(config)
    if workers is not None and (int(workers) != workers or workers < 1):
        raise ValueError(f"`workers` = {workers}; use a whole number >= 1.")
    out = Path(cfg.out_dir) / "study"
    stamp = out / "config.json"
    if stamp.is_file():
        old = json.loads(stamp.read_text())
        if old.get("reference_key") != cfg.reference_key():
            raise ValueError(
                f"{out} holds a study of another reference head (its [study.reference] differs); "
                "choose another out_dir or delete that folder.")
    rc = cfg.reference
    src = {"labels": ("labels_path", rc.labels_path), "mesh": ("mesh_path", rc.mesh_path),
           "scan": ("scan_path", rc.scan_path)}.get(rc.source)
    if src and not Path(src[1]).is_file():
        raise ValueError(f"[study.reference] {src[0]} = {src[1]!r} does not exist; pass the path "
                         "of the reference head's file (relative to where the study runs).")
    client, cluster = connect(workers, scheduler)  # an unreachable scheduler fails here
    try:
        (out / "samples").mkdir(parents=True, exist_ok=True)
        with atomic_write_path(stamp) as tmp:
            tmp.write_text(json.dumps({"reference_key": cfg.reference_key(),
                                       "config": cfg.to_dict()}, indent=1, default=str))
        cfgd = json.loads(json.dumps(cfg.to_dict(), default=list))
        samples = expand_samples(cfg)
        done, stale = finished_samples(samples, out / "samples", retry_failed=cfg.retry_failed)
        todo = [s for s in samples if s["sample"] not in done]
        logger.info("study %s: %d samples, %d already done, %d stale (their parameters, the "
                    "measures or the reference changed) run again", cfg.name, len(samples),
                    len(done), stale)
        t_start = time.perf_counter()
        ref_path = client.submit(prepare_reference, cfgd, str(out / "reference"),
                                 pure=False).result()
        fo_path = out / "first_order" / "first_order.json"
        need_fo = cfg.first_order and any(p.kind == "grf" for p in cfg.perturbations)
        morph_todo = [s for s in todo if s["route"] == "morph"]
        other = [s for s in todo if s["route"] != "morph"]
        # The first-order task goes first (priority): the morph samples wait for it, the
        # re-mesh and electrode samples run beside it on the other workers.
        fo_future, fo_error = None, None
        futures = []
        fo_key = cfg.first_order_key()
        if need_fo and (not fo_path.is_file()
                        or json.loads(fo_path.read_text()).get("key") != fo_key):
            fo_future = client.submit(run_first_order, cfgd, ref_path, str(out), pure=False,
                                      priority=10)
            futures.append(fo_future)
        futures += [client.submit(run_sample, s, cfgd, ref_path, str(out), pure=False)
                    for s in other]
        if fo_future is None:
            futures += [client.submit(run_sample, s, cfgd, ref_path, str(out), pure=False)
                        for s in morph_todo]
        bar = _bar(progress, len(samples), len(done))
        rows = dict(done)
        ac = as_completed(futures)
        for fut in ac:
            if fut is fo_future:
                try:
                    res = fut.result()
                except Exception as e:  # noqa: BLE001 (the samples still run; summary says why)
                    fo_error = f"{type(e).__name__}: {str(e).splitlines()[0][:300]}"
                    logger.warning("first-order task failed: %s", fo_error)
                else:
                    with atomic_write_path(fo_path) as tmp:
                        tmp.write_text(json.dumps({**res, "key": fo_key}, indent=1))
                for s in morph_todo:
                    ac.add(client.submit(run_sample, s, cfgd, ref_path, str(out), pure=False))
                continue
            res = fut.result()
            rows[res["sample"]] = res
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        wall = time.perf_counter() - t_start
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    ordered = [rows[s["sample"]] for s in samples]
    write_csv(out / "samples.csv", COLUMNS, ordered)
    fo = json.loads(fo_path.read_text()) if fo_path.is_file() else None
    if fo is not None and fo.get("key") != fo_key:
        fo = None  # stale, and its recomputation failed (summary.json's first_order_error)
    summary = summarise(ordered, fo)
    if fo_error:
        summary["first_order_error"] = fo_error
    summary["run"] = {"samples": len(samples), "skipped_finished": len(done),
                      "stale_rerun": stale,
                      "ran": len(todo), "wall_seconds": wall,
                      "workers": workers, "scheduler": scheduler}
    with atomic_write_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1, default=_json_default))
    _figures(out, ordered)
    return out


def finished_samples(samples: list[dict], folder: Path, *, retry_failed: bool = False
                     ) -> tuple[dict[str, dict], int]:
    """The samples a rerun can reuse: ({id: row}, number of stale files).

    A sample file is reused only when its stored `key` equals the expanded sample's
    (`StudyConfig.sample_key`); a file written under other parameters, measures or reference
    (or by a version that stored no key) is stale and its sample runs again. With
    `retry_failed`, failed samples run again too.
    """
    done, stale = {}, 0
    for s in samples:
        p = Path(folder) / f"{s['sample']}.json"
        if not p.is_file():
            continue
        row = json.loads(p.read_text())
        if row.get("key") != s["key"]:
            stale += 1
        elif not (retry_failed and row.get("error")):
            done[s["sample"]] = row
    return done, stale


def _bar(progress, total, initial):
    if progress is None:
        progress = sys.stderr.isatty()
    if not progress:
        return None
    return tqdm(total=total, initial=initial, desc="samples", unit="sample")


def _num(x):
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def summarise(rows: list[dict], first_order: dict | None) -> dict:
    """Per (perturbation, tissue, amplitude): n, failures, mean/sd/quantiles of every measure;
    for grf groups the sampled-vs-first-order comparison."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["perturbation"], r["tissue"], _num(r["amplitude"]), r["route"],
                           _num(r.get("bias_percent") or 0), r.get("settings") or ""), []).append(r)
    out = {"groups": []}
    agreement = {"measure": AGREEMENT_MEASURE, "bar": AGREEMENT_BAR,
                 "applies_to": f"grf samples (morph route) with sd <= {AGREEMENT_MAX_SD_MM} mm",
                 "groups": []}
    numeric = [*MEASURE_COLUMNS, "seconds", "min_scaled_jacobian",
               "rel_voltage_change_first_order", "linearisation_error", "second_order_rel_error",
               *DICE_COLUMNS]
    for (kind, tissue, amp, route, bias, settings), rs in groups.items():
        ok = [r for r in rs if not r.get("error")]
        g = {"perturbation": kind, "tissue": tissue, "amplitude": amp, "route": route,
             **({"bias_percent": bias, "settings": settings} if kind == "resegment" else {}),
             "n": len(rs), "n_failed": len(rs) - len(ok),
             "errors": sorted({r["error"] for r in rs if r.get("error")})[:5], "measures": {}}
        for c in numeric:
            v = np.array([_num(r.get(c)) for r in ok])
            v = v[np.isfinite(v)]
            if v.size:
                g["measures"][c] = {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                                    "q05": float(np.quantile(v, 0.05)), "q50": float(np.median(v)),
                                    "q95": float(np.quantile(v, 0.95)), "n": int(v.size)}
        if kind == "grf" and first_order:
            g["first_order"] = cmp = _first_order_comparison(ok, first_order, tissue, amp)
            if "per_sample_linearisation_error_max" in cmp and amp <= AGREEMENT_MAX_SD_MM:
                agreement["groups"].append({
                    "tissue": tissue, "sd_mm": amp, "n": cmp["per_sample_n"],
                    "max": cmp["per_sample_linearisation_error_max"],
                    "mean": cmp["per_sample_linearisation_error_mean"],
                    **{k: cmp[k] for k in (
                        "second_order_max", "second_order_mean", "sampled_n",
                        "sampled_rms_rel_voltage_change", "first_order_rms_rel_voltage_change",
                        "rms_ratio_sampled_over_first_order", "rms_ratio_sampling_sd",
                        "second_order_seconds_per_sample")
                       if k in cmp}})
        out["groups"].append(g)
    if agreement["groups"]:
        ag = agreement["groups"]
        worst = max(a["max"] for a in ag)
        agreement.update(max=worst, met=bool(worst < AGREEMENT_BAR))
        so = [a for a in ag if "second_order_max" in a]
        if so:
            w2 = max(a["second_order_max"] for a in so)
            agreement["second_order"] = {
                "measure": SECOND_ORDER_MEASURE, "max": w2,
                "mean": float(np.average([a["second_order_mean"] for a in so],
                                         weights=[a["n"] for a in so])),
                "within_bar": bool(w2 < AGREEMENT_BAR),
                "seconds_per_sample": float(np.average(
                    [a.get("second_order_seconds_per_sample", np.nan) for a in so],
                    weights=[a["n"] for a in so]))}
        rms = [a for a in ag if "rms_ratio_sampled_over_first_order" in a]
        if rms:
            agreement["distribution"] = {
                "measure": DISTRIBUTION_MEASURE,
                "groups": [{"tissue": a["tissue"], "sd_mm": a["sd_mm"], "n": a["sampled_n"],
                            "sampled_rms": a["sampled_rms_rel_voltage_change"],
                            "first_order_rms": a["first_order_rms_rel_voltage_change"],
                            "ratio": a["rms_ratio_sampled_over_first_order"],
                            "ratio_sampling_sd": a.get("rms_ratio_sampling_sd")} for a in rms],
                "max_abs_ratio_minus_1": max(abs(a["rms_ratio_sampled_over_first_order"] - 1)
                                             for a in rms)}
        out["agreement"] = agreement
    if first_order:
        out["first_order"] = first_order
    return out


def _first_order_comparison(ok: list[dict], first_order: dict, tissue: str, amp: float) -> dict:
    """Sampled vs first-order (and second-order) figures of one grf group's finished samples."""
    pred = [p for p in first_order["predictions"]
            if p["tissue"] == tissue and p["amplitude"] == amp]
    rel = np.array([_num(r.get("rel_voltage_change")) for r in ok])
    lin = np.array([_num(r.get("linearisation_error")) for r in ok])
    sec = np.array([_num(r.get("second_order_rel_error")) for r in ok])
    cmp = {"sampled_rms_rel_voltage_change": float(np.sqrt(np.mean(rel**2))) if rel.size else None,
           "sampled_n": int(rel.size)}
    if pred:
        p = pred[0]
        cmp["first_order_rms_rel_voltage_change"] = p["rms_rel_voltage_change"]
        cmp["first_order_rms_change_over_noise"] = p["rms_change_over_noise"]
        cmp.update({k: v for k, v in p.items() if k.startswith("sigma_sd_percent")})
        if rel.size:
            cmp["rms_ratio_sampled_over_first_order"] = (cmp["sampled_rms_rel_voltage_change"]
                                                         / p["rms_rel_voltage_change"])
            if np.isfinite(p.get("effective_dof", np.nan)):
                # the ratio's Monte Carlo scatter for rel.size independent samples (first order)
                cmp["first_order_effective_dof"] = p["effective_dof"]
                cmp["rms_ratio_sampling_sd"] = float(np.sqrt(1 / (2 * rel.size
                                                                  * p["effective_dof"])))
    if np.isfinite(lin).any():
        cmp["per_sample_n"] = int(np.isfinite(lin).sum())
        cmp["per_sample_linearisation_error_max"] = float(np.nanmax(lin))
        cmp["per_sample_linearisation_error_mean"] = float(np.nanmean(lin))
        cmp["agree_within_10_percent"] = bool(np.nanmax(lin) < AGREEMENT_BAR)
        cmp["criterion"] = AGREEMENT_MEASURE
    if np.isfinite(sec).any():
        cmp["second_order_max"] = float(np.nanmax(sec))
        cmp["second_order_mean"] = float(np.nanmean(sec))
        cmp["second_order_criterion"] = SECOND_ORDER_MEASURE
        secs = [_num((r.get("timings") or {}).get("second_order")) for r in ok]
        secs = [x for x in secs if np.isfinite(x)]
        if secs:
            cmp["second_order_seconds_per_sample"] = float(np.mean(secs))
    return cmp


def _figures(out: Path, rows: list[dict]):
    """Distributions of the main measures per (perturbation, tissue, amplitude)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if not r.get("error")]
    if not ok:
        return

    def label(r):
        extra = (f" bias {r['bias_percent']}" if _num(r.get("bias_percent") or 0) else "") + \
            (f" {r['settings']}" if r.get("settings") else "")
        return f"{r['perturbation']} {r['tissue']} {r['amplitude']}{extra}"

    labels = sorted({label(r) for r in ok})
    cols = ["rel_voltage_change", "voltage_change_over_noise", "localisation_error_mm",
            "image_correlation", "sigma_bias_percent_skull", "sigma_bias_percent_brain"]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for ax, c in zip(axes.ravel(), cols):
        data = [[_num(r[c]) for r in ok if label(r) == lab] for lab in labels]
        data = [[v for v in d if np.isfinite(v)] or [np.nan] for d in data]
        ax.boxplot(data, showmeans=True)
        for i, d in enumerate(data):
            ax.plot(np.full(len(d), i + 1.0), d, ".", alpha=0.6)
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=30, ha="right", fontsize=7)
        ax.set_title(c, fontsize=9)
    fig.tight_layout()
    with atomic_write_path(out / "distributions.png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
