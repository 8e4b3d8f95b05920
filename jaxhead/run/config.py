"""Run configuration: one frozen dataclass per stage, loaded from TOML.

Stage configs live beside their stage (``LayerConfig`` in ``segment/layers.py`` ...); this module
composes them into a :class:`RunConfig` and loads it from a TOML file, rejecting unknown keys with the
closest valid key suggested.
"""

import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .._tables import from_dict
from ..electrodes import ElectrodeConfig
from ..geometry.layers import LayerConfig
from ..geometry.surface import SurfaceConfig
from ..geometry.tetrahedralize import MeshConfig
from ..io import MEASUREMENT_FORMATS, MESH_EXTENSIONS
from ..io.measurements import LENGTH_UNITS
from ..inverse.fit import CSF_PRIOR
from ..protocol import ProtocolConfig, common_reference
from ..segmentation import SegmentConfig
from ..tissue import DEFAULT_SIGMA_S_M, TISSUE_NAMES

Modality = Literal["mri", "ct"]

#: `[inverse] fit_reject_sigma` for a recording when unset: channels beyond 5 robust standard
#: deviations are rejected (experiments/measured_fit.py: every channel corrupted by 20 % was
#: 27+ SD out, the clean ones below 5 once the fit had converged).
MEASURED_REJECT_SIGMA = 5.0


def is_pattern(path: str) -> bool:
    """Whether `path` is a glob pattern (has `*`, `?` or `[`)."""
    return any(c in path for c in "*?[")


@dataclass(frozen=True, kw_only=True)
class InputConfig:
    """Where the subject comes from.

    Arguments:
        source: "phantom" builds synthetic heads (no files needed); "file" loads `path`;
            "mesh" starts from a tetrahedral head mesh made elsewhere (`mesh_path`): the
            segment, layers and surfaces stages are then skipped (each writes skipped.txt
            saying so) and the mesh stage takes the loaded mesh instead of meshing.
        modalities: with source="phantom", one subject per modality ("mri", "ct").
        modality: with source="file", the scan's modality.
        path: with source="file", a NIfTI/Analyze volume; or a cohort: a glob pattern
            ("data/sub-*/anat/*_T1w.nii.gz", `**` for any depth) or a list of files and
            patterns, one subject each (`jaxhead.run.pipeline.subjects` names them: the
            BIDS `sub-XX` and `ses-YY` entities when the path has them, else the file
            name without its extension). Relative paths are relative to the current folder.
        labels_path: optional label map (0..4) to use instead of segmenting (one scan only).
        voxel_mm: phantom voxel size, or the size to resample a loaded scan to (None keeps it).
        seed: phantom subject seed.
        noise: phantom noise level (MRI: fraction of white-matter intensity; CT: HU); None = default.
        mesh_path: with source="mesh", a .msh (Gmsh/SimNIBS), .vtu or .mat (jaxhead, EIDORS)
            mesh, read by `jaxhead.io.load_mesh`.
        tissue_map: the file's tissue labels or names -> "brain" | "csf" | "skull" | "scalp"
            (keys: labels as strings, e.g. {"1" = "brain", "2" = "brain", "3" = "csf", ...},
            or the file's tissue names), or "simnibs" (`jaxhead.io.SIMNIBS_TISSUE_MAP`; a
            SimNIBS head with eyes, blood and muscle needs all its tags in a table). Default:
            the file's own tissue names, or jaxhead's labels 1..4.
        mesh_units: length unit of an EIDORS mesh's vtx ("mm", "cm", "m"); default mm.
        facing: a head facing away from +y (RAS) is an error ("check"), turned about z with
            a report ("reorient"), or taken as it is ("ignore"); see `load_mesh`.
        reorient_tets: fix negatively oriented tets (counted in the input stage's report).
    """

    source: Literal["phantom", "file", "mesh"] = "phantom"
    modalities: tuple[Modality, ...] = ("mri", "ct")
    modality: Modality = "mri"
    path: str | tuple[str, ...] | None = None
    labels_path: str | None = None
    voxel_mm: float | None = 2.0
    seed: int = 0
    noise: float | None = None
    mesh_path: str | None = None
    tissue_map: dict[str, str] | Literal["simnibs"] | None = None
    mesh_units: Literal["mm", "cm", "m"] | None = None
    facing: Literal["check", "reorient", "ignore"] = "check"
    reorient_tets: bool = False

    def __post_init__(self):
        if self.source not in ("phantom", "file", "mesh"):
            raise ValueError(f'[input] `source` = {self.source!r}; use "phantom", "file" or "mesh".')
        if self.source == "file" and not self.path:
            raise ValueError('[input] source = "file" needs `path` = "scan.nii.gz" (or a cohort: '
                             'a pattern "data/sub-*/anat/*_T1w.nii.gz" or a list of files).')
        if self.path is not None and self.source != "file":
            raise ValueError(f"[input] `path` = {self.path!r} is set but source = "
                             f"{self.source!r}; set source = \"file\" to read that scan, or "
                             "remove path.")
        if self.is_cohort and self.labels_path is not None:
            raise ValueError(f"[input] `labels_path` = {self.labels_path!r} is one label map but "
                             f"`path` = {self.path!r} is a cohort of scans; remove labels_path "
                             "(each scan is segmented), or run each scan with its labels.")
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise ValueError(f"[input] `voxel_mm` must be > 0, got {self.voxel_mm}.")
        if self.source == "phantom" and not self.modalities:
            raise ValueError('[input] `modalities` is empty; use e.g. ["mri", "ct"].')
        if self.source == "mesh" and not self.mesh_path:
            raise ValueError('[input] source = "mesh" needs `mesh_path` = "head.msh" (.msh, .vtu '
                             'or .mat).')
        if self.mesh_path is not None:
            if self.source != "mesh":
                raise ValueError(f"[input] `mesh_path` = {self.mesh_path!r} is set but source = "
                                 f"{self.source!r}; set source = \"mesh\" to start the run from "
                                 "that mesh, or remove mesh_path.")
            if not Path(self.mesh_path).is_file():
                raise ValueError(f"[input] `mesh_path` = {self.mesh_path!r} is not a file "
                                 f"(relative paths are relative to the current directory, "
                                 f"{Path.cwd()}).")
            if Path(self.mesh_path).suffix.lower() not in MESH_EXTENSIONS:
                raise ValueError(f"[input] `mesh_path` = {self.mesh_path!r}: unsupported "
                                 f"extension; use one of {list(MESH_EXTENSIONS)}.")
        elif any(v is not None for v in (self.tissue_map, self.mesh_units)) \
                or self.facing != "check" or self.reorient_tets:
            raise ValueError("[input] `tissue_map`, `mesh_units`, `facing` and `reorient_tets` "
                             "apply to a mesh file; set source = \"mesh\" and `mesh_path`.")
        if isinstance(self.tissue_map, str) and self.tissue_map != "simnibs":
            raise ValueError(f"[input] `tissue_map` = {self.tissue_map!r}; use \"simnibs\" or a "
                             'table {"<label or name>" = "brain" | "csf" | "skull" | "scalp"}.')
        if isinstance(self.tissue_map, dict):
            for k, v in self.tissue_map.items():
                if str(v).lower() not in TISSUE_NAMES:
                    raise ValueError(f"[input] `tissue_map.{k}` = {v!r}; use one of "
                                     f"{list(TISSUE_NAMES)}.")
        if self.mesh_units is not None and self.mesh_units not in LENGTH_UNITS:
            raise ValueError(f"[input] `mesh_units` = {self.mesh_units!r}; use one of "
                             f"{sorted(LENGTH_UNITS)}.")
        if self.facing not in ("check", "reorient", "ignore"):
            raise ValueError(f'[input] `facing` = {self.facing!r}; use "check", "reorient" or '
                             '"ignore".')

    @property
    def is_cohort(self) -> bool:
        """`path` is a glob pattern or a list: one subject per file (folders named by subject)."""
        return self.source == "file" and (
            isinstance(self.path, tuple) or (isinstance(self.path, str) and is_pattern(self.path)
                                             and not Path(self.path).is_file()))

    def mesh_tissue_map(self):
        """`tissue_map` as `load_mesh` takes it: label keys ("3") as ints, names as given."""
        if not isinstance(self.tissue_map, dict):
            return self.tissue_map
        return {int(k) if str(k).strip().lstrip("-").isdigit() else k: str(v).lower()
                for k, v in self.tissue_map.items()}


@dataclass(frozen=True, kw_only=True)
class ExportConfig:
    """Mesh files to write: any of "vtu" (ParaView), "msh" (Gmsh 2.2), "mat" (MATLAB/EIDORS)."""

    formats: tuple[Literal["vtu", "msh", "mat"], ...] = ("vtu", "msh", "mat")


@dataclass(frozen=True, kw_only=True)
class ForwardConfig:
    """The forward simulation of the pipeline.

    Arguments:
        sigma_s_m: conductivity per tissue in S/m (keys brain, csf, skull, scalp); missing keys
            take the defaults of `jaxhead.tissue.DEFAULT_SIGMA_S_M`.
        solver: "direct" (sparse factorisation on the host) or "cg" (pure-JAX block CG).
        plot_injection: which injection (row of `Protocol.injections`) the scalp PNG shows.
    """

    sigma_s_m: dict[str, float] = field(default_factory=lambda: dict(zip(TISSUE_NAMES, DEFAULT_SIGMA_S_M)))
    solver: Literal["direct", "cg"] = "direct"
    plot_injection: int = 0

    def __post_init__(self):
        if isinstance(self.plot_injection, bool) or not isinstance(self.plot_injection, int) \
                or self.plot_injection < 0:
            raise ValueError(f"[forward] `plot_injection` must be an integer >= 0 (a row of the "
                             f"protocol's injections), got {self.plot_injection!r}.")
        for k, v in self.sigma_s_m.items():
            if k not in TISSUE_NAMES:
                raise ValueError(f"[forward] `sigma_s_m` has key {k!r}; use {list(TISSUE_NAMES)}.")
            if not v > 0:
                raise ValueError(f"[forward] `sigma_s_m.{k}` must be > 0 S/m, got {v}.")

    def sigma(self):
        """(4,) conductivities in S/m, ordered BRAIN, CSF, SKULL, SCALP."""

        d = dict(zip(TISSUE_NAMES, DEFAULT_SIGMA_S_M)) | dict(self.sigma_s_m)
        return np.array([d[n] for n in TISSUE_NAMES], dtype=np.float64)


@dataclass(frozen=True, kw_only=True)
class InverseConfig:
    """The inverse stage: a perturbation reconstruction and a conductivity fit on simulated data.

    Arguments:
        centre_mm: centre of the spherical brain perturbation (world mm); None puts it 40 % of the
            way from the brain's centroid to its top (a cortical target).
        radius_mm: perturbation radius (mm); rel_change: its relative conductivity change.
        noise_percent: Gaussian noise per channel, % of the baseline voltage (the seed paper: 0.5).
        cell_mm: reconstruction grid cell size (mm; the Jacobian is summed into brain cells).
        method: "tsvd" or "tikhonov" (truncation / lambda chosen by GCV).
        fit: also fit the four tissue conductivities: to `measured_path`'s voltages when given,
            else to noisy simulated ones.
        fit_init_s_m: the fit's starting conductivities (brain, csf, skull, scalp).
        measured_path: measured voltages for the fit (`jaxhead.protocol.load_voltages`: five
            columns source, sink, meas+, meas-, volts with 1-based electrodes, as the forward
            stage's voltages.csv, or one column of volts in protocol order); the rows must be
            the configured protocol's. `noise_percent` of each measured voltage is the fit's
            noise model.
        noise_floor: the fit's noise refers to max(|V|, noise_floor * RMS(V)) per channel
            (`jaxhead.inverse.noise_std`). 0 is the pure per-channel model. Measured data carry
            modelling error the noise model does not, and channels with a near-zero standing
            voltage then dominate: without the error model below, 0.1 turned a diverging
            cross-mesh fit into one 9 % off in brain and CSF (experiments/cross_mesh_fit.py).
        approx_error_mesh: a finer mesh of the same head (e.g. a run's mesh.vtu at smaller
            [mesh] edge_mm): the fit then uses the approximation-error model of this run's mesh
            against it (`jaxhead.approximation_error`, same electrode centres and radius),
            which removes the bias a coarse mesh puts into brain and CSF.
        approx_error_draws: prior draws for that model (`jaxhead.sample_conductivities`
            around the [forward] conductivities; each costs one solve on each mesh).
        seed: noise seed of the reconstruction's data; the fit's simulated data use seed + 1
            and the approximation-error draws seed + 2 (independent streams from one seed).
        centre_height_fraction: with centre_mm = None, the perturbation sits this fraction of
            the way from the brain's centroid up to its top (0.4: a cortical target).
        reconstruct_noise_floor: the reconstruction's whitening refers to max(|V0|, floor *
            RMS(V0)) per channel (`jaxhead.inverse.noise_std`), so that channels with a
            near-zero standing voltage are not trusted beyond the mesh's accuracy (0.03:
            tests/test_inverse_recovery.py).
        noser_exponent: column normalisation of the reconstruction (`TSVD(normalise=...)`;
            EIDORS prior_noser). 0.5, half NOSER: full NOSER (1) lifts deep cells on heads.
        fit_rtol, fit_atol: the fit's convergence tolerances (optimistix rtol/atol).
        fit_max_steps: the fit's step limit.
        reconstruct: run the simulated-perturbation reconstruction (set false for a run that
            only fits a recording).

    A recording (`measured_path` read by `jaxhead.io.load_measurements`) brings its own
    protocol (rows and current) and electrodes; these keys say how it is read and fitted:

        measured_format: "csv" (our CSV or the plain layout), "ucl" (UCL JSON settings +
            .mat/.json voltages in mV) or "voltages" (the old `load_voltages` reading: five
            columns or one column of volts in the configured [protocol]'s order, fitted with
            the [electrodes] and [protocol] of the config). Default: "ucl" for .json, "csv"
            for a file whose rows name electrodes, else "voltages".
        measured_voltages_path: UCL layout: the voltages file (default: the settings'
            `Voltages` entry, else the .mat beside the JSON with its stem, which is then
            named here so that the run's fingerprint covers it).
        measured_variable: UCL layout: the .mat/.json variable holding the voltages.
        measured_current_a: injected current in A, overriding the file's.
        measured_electrodes: where the recording's electrodes go on the head: "names" (placed
            by their 10-10 / 10-5 names, `[electrodes] landmarks_mm` as for layouts),
            "positions" (the file's coordinates registered to the scalp,
            `jaxhead.electrodes.register_positions`, residual in registration.txt), "config"
            (the [electrodes] layout; the counts must agree), or "auto" (names when every
            name is known, else positions when the file has them, else the config).
        frequency_hz: the frequency to fit (Hz; it must be in the file), or "all" (a fit per
            frequency: spectrum.csv and spectrum.png), or a list of frequencies. Default: the
            file's only frequency (an error naming them when it has several).
        fit_tissues: the tissues to fit; the others stay at `fit_init_s_m`.
        fit_gain: fit an unknown current gain (a global scale). Default: true for a recording,
            false for simulated data. With the gain, conductivities are determined only up to
            a common scale: one tissue must be left out of `fit_tissues` or have a prior in
            `fit_priors`; if neither, CSF's prior (1.79 S/m +- 2 %, Baumann et al. 1997) is
            added and fit.txt says so.
        fit_offsets: "per_injection" (a free voltage offset per injection: the reference
            electrode's unknown potential) or "none". Default: "per_injection" for a recording
            whose rows share one reference electrode, else "none".
        fit_contact_impedance: "fixed" ([electrodes] contact_impedance_ohm_m2), "common" (one
            fitted factor) or "per_electrode". Default for a recording: "per_electrode" when
            every current-carrying electrode is also measured while it carries current (the
            only rows that determine its impedance), else "common"; "fixed" for simulated data.
        fit_contact_prior: with per-electrode contact impedances, a log-normal prior around
            the [electrodes] value with this geometric standard deviation (> 1; 0: none).
        fit_priors: {tissue or "gain" = [value, relative sd]} log-normal priors.
        fit_loss: "linear", "huber" or "cauchy" (robust, on residuals in noise standard
            deviations, scale `fit_loss_scale`). Default: "cauchy" for a recording, else
            "linear".
        fit_loss_scale: the robust loss's scale (noise standard deviations).
        fit_reject_sigma: reject channels whose residual exceeds this many robust standard
            deviations and refit (rejected.csv lists them). Default: 5 for a recording, off
            for simulated data; 0 turns it off.
    """

    centre_mm: tuple[float, float, float] | None = None
    radius_mm: float = 15.0
    rel_change: float = 0.2
    noise_percent: float = 0.5
    cell_mm: float = 8.0
    method: Literal["tsvd", "tikhonov"] = "tsvd"
    fit: bool = True
    fit_init_s_m: tuple[float, float, float, float] = (0.2, 1.0, 0.03, 0.3)
    measured_path: str | None = None
    noise_floor: float = 0.0
    approx_error_mesh: str | None = None
    approx_error_draws: int = 20
    seed: int = 0
    centre_height_fraction: float = 0.4
    reconstruct_noise_floor: float = 0.03
    noser_exponent: float = 0.5
    fit_rtol: float = 1e-6
    fit_atol: float = 1e-6
    fit_max_steps: int = 50
    reconstruct: bool = True
    measured_format: Literal["csv", "ucl", "voltages"] | None = None
    measured_voltages_path: str | None = None
    measured_variable: str | None = None
    measured_current_a: float | None = None
    measured_electrodes: Literal["auto", "names", "positions", "config"] = "auto"
    frequency_hz: float | Literal["all"] | tuple[float, ...] | None = None
    fit_tissues: tuple[str, ...] = TISSUE_NAMES
    fit_gain: bool | None = None
    fit_offsets: Literal["none", "per_injection"] | None = None
    fit_contact_impedance: Literal["fixed", "common", "per_electrode"] | None = None
    fit_contact_prior: float = 2.0
    fit_priors: dict[str, tuple[float, float]] = field(default_factory=dict)
    fit_loss: Literal["linear", "huber", "cauchy"] | None = None
    fit_loss_scale: float = 3.0
    fit_reject_sigma: float | None = None

    def __post_init__(self):
        self._check_measured()
        for name in ("radius_mm", "cell_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"[inverse] `{name}` must be > 0, got {getattr(self, name)}.")
        if not self.rel_change > -1:
            raise ValueError(f"[inverse] `rel_change` must be > -1, got {self.rel_change}.")
        if not self.noise_percent >= 0:
            raise ValueError(f"[inverse] `noise_percent` must be >= 0, got {self.noise_percent}.")
        for name in ("noise_floor", "reconstruct_noise_floor", "noser_exponent"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"[inverse] `{name}` must be >= 0, got {getattr(self, name)}.")
        if not 0 <= self.centre_height_fraction <= 1:
            raise ValueError("[inverse] `centre_height_fraction` must be in [0, 1] (0: the brain's "
                             f"centroid, 1: its top), got {self.centre_height_fraction}.")
        for name in ("fit_rtol", "fit_atol"):
            if not getattr(self, name) > 0:
                raise ValueError(f"[inverse] `{name}` must be > 0, got {getattr(self, name)}.")
        if isinstance(self.fit_max_steps, bool) or not isinstance(self.fit_max_steps, int) \
                or self.fit_max_steps < 1:
            raise ValueError(f"[inverse] `fit_max_steps` must be an integer >= 1, got "
                             f"{self.fit_max_steps!r}.")
        for name in ("measured_path", "approx_error_mesh"):
            value = getattr(self, name)
            if value is not None and not Path(value).is_file():
                raise ValueError(f"[inverse] `{name}` = {value!r} is not a file (relative paths "
                                 f"are relative to the current directory, {Path.cwd()}).")
        if isinstance(self.approx_error_draws, bool) or not isinstance(self.approx_error_draws, int) \
                or self.approx_error_draws < 2:
            raise ValueError("[inverse] `approx_error_draws` must be an integer >= 2, got "
                             f"{self.approx_error_draws!r}.")

    def _check_measured(self):
        """The recording keys: each wrong value names the key, the value and the fix."""
        c = self
        fmt_keys = ("measured_format", "measured_voltages_path", "measured_variable",
                    "measured_current_a", "frequency_hz")
        if c.measured_path is None:
            given = [k for k in fmt_keys if getattr(c, k) is not None]
            if c.measured_electrodes != "auto":
                given.append("measured_electrodes")
            if given:
                raise ValueError(f"[inverse] {', '.join(f'`{k}`' for k in given)} describe a "
                                 "recording, but `measured_path` is not set; set it or remove "
                                 "them.")
        elif Path(c.measured_path).is_file():
            fmt = c.measured_format
            if fmt is not None and fmt not in MEASUREMENT_FORMATS + ("voltages",):
                raise ValueError(f"[inverse] `measured_format` = {fmt!r}; use \"csv\", \"ucl\" or "
                                 "\"voltages\".")
            if fmt is None:
                object.__setattr__(self, "measured_format", measured_format_of(c.measured_path))
            if self.measured_format == "ucl" and c.measured_voltages_path is None:
                # name the implicit voltages file so that the resume fingerprint covers it
                beside = ucl_voltages_beside(c.measured_path)
                if beside is not None:
                    object.__setattr__(self, "measured_voltages_path", beside)
            if self.measured_format == "voltages":
                extra = [k for k in fmt_keys[1:] if getattr(c, k) is not None]
                if c.measured_electrodes != "auto":
                    extra.append("measured_electrodes")
                if extra:
                    raise ValueError(
                        f"[inverse] {', '.join(f'`{k}`' for k in extra)} need a recording "
                        "layout, but `measured_format` is \"voltages\" (volts in the configured "
                        "[protocol]'s order); use measured_format = \"csv\" or \"ucl\".")
        if c.measured_voltages_path is not None and not Path(c.measured_voltages_path).is_file():
            raise ValueError(f"[inverse] `measured_voltages_path` = {c.measured_voltages_path!r} "
                             f"is not a file (relative paths are relative to {Path.cwd()}).")
        if c.measured_current_a is not None and not (
                isinstance(c.measured_current_a, (int, float)) and c.measured_current_a > 0):
            raise ValueError(f"[inverse] `measured_current_a` must be > 0 A, got "
                             f"{c.measured_current_a!r}.")
        if c.measured_electrodes not in ("auto", "names", "positions", "config"):
            raise ValueError(f"[inverse] `measured_electrodes` = {c.measured_electrodes!r}; use "
                             "\"auto\", \"names\", \"positions\" or \"config\".")
        f = c.frequency_hz
        if isinstance(f, str):
            if f != "all":
                raise ValueError(f"[inverse] `frequency_hz` = {f!r}; give a frequency in Hz, a "
                                 "list of them, or \"all\".")
        elif f is not None:
            vals = f if isinstance(f, (tuple, list)) else (f,)
            if not vals or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                   and math.isfinite(x) and x > 0 for x in vals):
                raise ValueError(f"[inverse] `frequency_hz` = {f!r}; frequencies must be > 0 Hz "
                                 "(or \"all\").")
        tissues = c.fit_tissues
        if isinstance(tissues, str) or not tissues or any(
                str(t).lower() not in TISSUE_NAMES for t in tissues) \
                or len(set(map(str.lower, tissues))) != len(tissues):
            raise ValueError(f"[inverse] `fit_tissues` = {tissues!r}; list distinct tissues from "
                             f"{list(TISSUE_NAMES)}.")
        if c.fit_gain is not None and not isinstance(c.fit_gain, bool):
            raise ValueError(f"[inverse] `fit_gain` must be true or false, got {c.fit_gain!r}.")
        if c.fit_offsets not in (None, "none", "per_injection"):
            raise ValueError(f"[inverse] `fit_offsets` = {c.fit_offsets!r}; use \"none\" or "
                             "\"per_injection\".")
        if c.fit_contact_impedance not in (None, "fixed", "common", "per_electrode"):
            raise ValueError(f"[inverse] `fit_contact_impedance` = {c.fit_contact_impedance!r}; "
                             "use \"fixed\", \"common\" or \"per_electrode\".")
        if not (c.fit_contact_prior == 0 or c.fit_contact_prior > 1):
            raise ValueError(f"[inverse] `fit_contact_prior` = {c.fit_contact_prior!r} is the "
                             "prior's geometric standard deviation: a factor > 1 (e.g. 2.0), or "
                             "0 for none.")
        for k, v in dict(c.fit_priors).items():
            if k not in TISSUE_NAMES + ("gain",):
                raise ValueError(f"[inverse] `fit_priors.{k}`: priors are for "
                                 f"{list(TISSUE_NAMES) + ['gain']}.")
            if len(v) != 2 or not (v[0] > 0 and v[1] > 0):
                raise ValueError(f"[inverse] `fit_priors.{k}` = {list(v)!r}; give [value, "
                                 "relative sd], both > 0, e.g. [1.79, 0.02].")
            if k != "gain" and k not in [t.lower() for t in tissues]:
                raise ValueError(f"[inverse] `fit_priors.{k}`: {k} is not in `fit_tissues` "
                                 f"{list(tissues)}; fit it or drop the prior.")
        if c.fit_loss not in (None, "linear", "huber", "cauchy"):
            raise ValueError(f"[inverse] `fit_loss` = {c.fit_loss!r}; use \"linear\", \"huber\" "
                             "or \"cauchy\".")
        if not c.fit_loss_scale > 0:
            raise ValueError(f"[inverse] `fit_loss_scale` must be > 0 (noise standard "
                             f"deviations), got {c.fit_loss_scale}.")
        if c.fit_reject_sigma is not None and not c.fit_reject_sigma >= 0:
            raise ValueError(f"[inverse] `fit_reject_sigma` must be >= 0 (0: no rejection), "
                             f"got {c.fit_reject_sigma}.")

    def fit_keywords(self, protocol, *, recording: bool) -> tuple[dict, list[str]]:
        """`fit_conductivities` keywords from these settings (unset keys: the defaults for a
        recording, `recording=True`, or for simulated data; see above), and notes for fit.txt
        saying what was chosen."""
        rows = np.asarray(protocol.rows)
        notes = []
        gain = self.fit_gain if self.fit_gain is not None else recording
        offsets = self.fit_offsets
        if offsets is None:
            offsets = ("per_injection" if recording and common_reference(protocol) is not None
                       else "none")
        z = self.fit_contact_impedance
        carrying = np.unique(rows[:, :2])
        unseen = [int(e) for e in carrying
                  if not np.any(((rows[:, 0] == e) | (rows[:, 1] == e))
                                & ((rows[:, 2] == e) | (rows[:, 3] == e)))]
        if z is None:
            z = "fixed" if not recording else ("common" if unseen else "per_electrode")
        loss = self.fit_loss or ("cauchy" if recording else "linear")
        reject = self.fit_reject_sigma
        if reject is None:
            reject = MEASURED_REJECT_SIGMA if recording else 0.0
        tissues = tuple(t.lower() for t in self.fit_tissues)
        priors = {k: tuple(v) for k, v in dict(self.fit_priors).items()}
        if gain and len(tissues) == 4 and not any(t in priors for t in tissues):
            priors["csf"] = CSF_PRIOR
            notes.append(f"prior added: csf {CSF_PRIOR[0]} S/m +- {100 * CSF_PRIOR[1]:.0f} % "
                         "(the gain leaves the conductivities' common scale to a prior; Baumann "
                         "et al. 1997); set [inverse] fit_priors or fit_tissues to choose another")
        contact_prior = (self.fit_contact_prior
                         if z == "per_electrode" and self.fit_contact_prior > 0 else None)
        notes.append(f"fit options: tissues {list(tissues)}, gain {gain}, offsets {offsets}, "
                     f"contact impedance {z}"
                     + (f" (prior: factor {contact_prior})" if contact_prior else "")
                     + f", loss {loss}"
                     + (f" (scale {self.fit_loss_scale})" if loss != "linear" else "")
                     + (f", rejection at {reject} robust SD" if reject else ", no rejection"))
        if z == "per_electrode":
            never = sorted(set(range(int(rows.max()) + 1)) - set(carrying.tolist()))
            if never:
                notes.append(f"electrodes {[e + 1 for e in never]} (1-based) never carry current: "
                             "their contact impedances are set by the prior (and weak shunting), "
                             "not by the data; read their standard errors")
            if unseen:
                notes.append(f"electrodes {[e + 1 for e in unseen]} (1-based) carry current but "
                             "are never measured while they do: their contact impedances are "
                             "weakly determined")
        kw = dict(fit=tissues, gain=bool(gain), offsets=None if offsets == "none" else offsets,
                  contact_impedance=False if z == "fixed" else z, contact_prior=contact_prior,
                  priors=priors or None, loss=loss, loss_scale=float(self.fit_loss_scale),
                  reject_sigma=float(reject) if reject else None)
        return kw, notes


def measured_format_of(path) -> str:
    """The `[inverse] measured_format` a file gets by default: "ucl" for .json, "csv" for a
    table whose rows name four electrodes, else "voltages" (one column of volts)."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        return "ucl"
    try:
        with open(path, encoding="utf-8") as fh:
            for line in fh:
                s = line.strip()
                if s and not s.startswith("#"):
                    cells = [x for x in s.replace(",", " ").replace("\t", " ").split() if x]
                    if len(cells) >= 5:
                        return "csv"
                    if len(cells) == 1 and cells[0].lower() not in ("volts", "voltage", "v"):
                        return "voltages"
    except (OSError, UnicodeDecodeError):
        return "csv"  # load_measurements then names what is wrong with the file
    return "voltages"


def ucl_voltages_beside(path) -> str | None:
    """The .mat beside a UCL settings JSON that `load_measurements` would read, when the JSON
    has no `Voltages` entry (None otherwise, or when the JSON cannot be read: the inverse
    stage then reports the file's problem)."""
    path = Path(path)
    try:
        settings = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    beside = path.with_suffix(".mat")
    if isinstance(settings, dict) and "Voltages" not in settings and beside.is_file():
        return str(beside)
    return None


@dataclass(frozen=True, kw_only=True)
class RunConfig:
    """A whole run: where to write, which stages, and each stage's config.

    Arguments:
        name: run name (used for the default output folder).
        out_dir: the run folder; relative paths are relative to the current directory.
        stages: the stages to run, in pipeline order (default: every stage available).
    """

    name: str = "run"
    out_dir: str | None = None
    stages: tuple[str, ...] | None = None
    input: InputConfig = field(default_factory=InputConfig)
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    layers: LayerConfig = field(default_factory=LayerConfig)
    surfaces: SurfaceConfig = field(default_factory=SurfaceConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    export: ExportConfig = field(default_factory=ExportConfig)
    electrodes: ElectrodeConfig = field(default_factory=ElectrodeConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    forward: ForwardConfig = field(default_factory=ForwardConfig)
    inverse: InverseConfig = field(default_factory=InverseConfig)

    def __post_init__(self):
        if self.stages is not None and len(self.stages) == 0:
            raise ValueError("`stages` is empty, so the run would do nothing; list the stages to "
                             "run, or leave `stages` out to run them all.")

    @property
    def run_dir(self) -> Path:
        return Path(self.out_dir if self.out_dir else f"runs/{self.name}")


def load_config(path: str | Path) -> RunConfig:
    """Read a TOML run config. Unknown keys raise ValueError with the closest valid key."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {str(path)!r} not found.")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not valid TOML: {e}") from None
    if not data:
        raise ValueError(
            f"{path}: the config is empty, so the run would be the built-in demo written to "
            "runs/run; set at least `out_dir` (and `stages`, [input]): start from "
            "configs/demo.toml.")
    try:
        return from_dict(RunConfig, data)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
