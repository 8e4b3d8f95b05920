"""Run configuration: one frozen dataclass per stage, loaded from TOML.

Stage configs live beside their stage (``LayerConfig`` in ``segment/layers.py`` ...); this module
composes them into a :class:`RunConfig` and loads it from a TOML file, rejecting unknown keys with the
closest valid key suggested.
"""

import collections.abc
import dataclasses
import difflib
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..electrodes import ElectrodeConfig
from ..geometry.layers import LayerConfig
from ..geometry.surface import SurfaceConfig
from ..geometry.tetrahedralize import MeshConfig
from ..protocol import ProtocolConfig
from ..segmentation import SegmentConfig
from ..tissue import DEFAULT_SIGMA_S_M, TISSUE_NAMES

Modality = Literal["mri", "ct"]


@dataclass(frozen=True, kw_only=True)
class InputConfig:
    """Where the subject comes from.

    Arguments:
        source: "phantom" builds synthetic heads (no files needed); "file" loads `path`.
        modalities: with source="phantom", one subject per modality ("mri", "ct").
        modality: with source="file", the scan's modality.
        path: with source="file", a NIfTI/Analyze volume.
        labels_path: optional label map (0..4) to use instead of segmenting.
        voxel_mm: phantom voxel size, or the size to resample a loaded scan to (None keeps it).
        seed: phantom subject seed.
        noise: phantom noise level (MRI: fraction of white-matter intensity; CT: HU); None = default.
    """

    source: Literal["phantom", "file"] = "phantom"
    modalities: tuple[Modality, ...] = ("mri", "ct")
    modality: Modality = "mri"
    path: str | None = None
    labels_path: str | None = None
    voxel_mm: float | None = 2.0
    seed: int = 0
    noise: float | None = None

    def __post_init__(self):
        if self.source == "file" and not self.path:
            raise ValueError('[input] source = "file" needs `path` = "scan.nii.gz".')
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise ValueError(f"[input] `voxel_mm` must be > 0, got {self.voxel_mm}.")
        if self.source == "phantom" and not self.modalities:
            raise ValueError('[input] `modalities` is empty; use e.g. ["mri", "ct"].')


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

    def __post_init__(self):
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


def _suggest(key: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.5)
    return f" Did you mean `{close[0]}`?" if close else f" Valid keys: {', '.join(sorted(valid))}."


def _convert(value: Any, tp: Any, where: str) -> Any:
    """Convert a TOML value to the annotated type (dataclass, tuple, Literal, mapping, scalar)."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise ValueError(f"`{where}` must be a table, got {value!r}.")
        return from_dict(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, where)
            except (ValueError, TypeError) as e:
                errors.append(str(e))
        raise ValueError(f"`{where}` = {value!r} does not fit {tp}: {'; '.join(errors)}")
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ValueError(f"`{where}` = {value!r}; choose one of {list(choices)}.")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"`{where}` must be a list, got {value!r}.")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ValueError(f"`{where}` needs {len(args)} entries, got {len(value)}.")
        return tuple(_convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(args, value)))
    if origin in (dict, collections.abc.Mapping) or tp in (dict,):
        if not isinstance(value, dict):
            raise ValueError(f"`{where}` must be a table, got {value!r}.")
        kt, vt = (typing.get_args(tp) + (Any, Any))[:2]
        return {_convert(k, kt, f"{where} key"): _convert(v, vt, f"{where}.{k}") for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"`{where}` must be a number, got {value!r}.")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"`{where}` must be an integer, got {value!r}.")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"`{where}` must be true or false, got {value!r}.")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ValueError(f"`{where}` must be a string, got {value!r}.")
        return value
    if isinstance(tp, type) and hasattr(tp, "parse"):  # e.g. Tissue keys given by name
        return tp.parse(value)
    return value


def from_dict(cls: type, data: dict, where: str = "") -> Any:
    """Build the frozen dataclass `cls` from a dict, rejecting unknown keys with a suggestion."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    kwargs = {}
    for key, value in data.items():
        name = f"{where}.{key}" if where else key
        if key not in fields:
            section = f"[{where}]" if where else "the top level"
            raise ValueError(f"unknown key `{key}` in {section}.{_suggest(key, list(fields))}")
        kwargs[key] = _convert(value, hints[key], name)
    try:
        return cls(**kwargs)
    except TypeError as e:
        raise ValueError(f"[{where or 'top level'}]: {e}") from None


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
