"""The `[study]` section: reference head, perturbations with their sample counts, measures, seeds.

One frozen dataclass per part (STYLE.md, Conventions 4); `load_study_config` reads TOML and
rejects unknown keys with the closest valid one, and every value is checked when the dataclass is
built, so bad input is one clear error before any work starts.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .._tables import fields_from_dict, from_dict
from ..segmentation import RegisterConfig, SegmentConfig
from ..tissue import DEFAULT_SIGMA_S_M, TISSUE_NAMES, Tissue
from .measures import MeasureConfig
from .perturb import LABEL_KINDS

#: Perturbation kinds, the routes that can realise them, and what `amplitude` means.
KINDS: dict[str, tuple[tuple[str, ...], str]] = {
    "grf": (("morph",), "sd in mm of a smooth random normal displacement of the interface"),
    **{k: (("remesh",), v) for k, v in LABEL_KINDS.items()},
    "resegment": (("remesh",), "sd of the noise added to the scan before it is segmented again, "
                  "in % of the scan's robust intensity range (P99 - P1 of all its voxels)"),
    "electrode_position": (("electrodes",), "sd in mm of each electrode's tangential shift"),
}
ROUTES = ("morph", "remesh", "electrodes")
_NEED_TISSUE = ("grf", "dilate", "erode")


def _closest(name: str, valid) -> str:
    m = difflib.get_close_matches(str(name), list(valid), n=1)
    return f" (did you mean {m[0]!r}?)" if m else ""


#: SegmentConfig fields a study may set ([study.reference] segment, a resegment perturbation's
#: settings); the modality is [study.reference] modality.
SEGMENT_SETTINGS = tuple(f.name for f in dataclasses.fields(SegmentConfig) if f.name != "modality")


def _check_settings(overrides, where: str) -> dict:
    """`overrides` as SegmentConfig keyword arguments, typed (`jaxhead._tables`); a `register`
    table stays a dict of checked RegisterConfig fields, applied over the base config's."""
    if not isinstance(overrides, dict):
        raise ValueError(f"{where} must be a table of SegmentConfig fields, e.g. {{beta = 0.2}}, "
                         f"got {overrides!r}.")
    if "modality" in overrides:
        raise ValueError(f"{where} sets `modality`; the scan's modality is [study.reference] "
                         "modality, remove it here.")
    rest = {k: v for k, v in overrides.items() if k != "register"}
    kw = fields_from_dict(SegmentConfig, rest, where)
    reg = overrides.get("register")
    if isinstance(reg, RegisterConfig):
        kw["register"] = reg
    elif reg is not None:
        kw["register"] = fields_from_dict(RegisterConfig, reg, f"{where}.register")
    return kw


def segment_config(modality: str, overrides: dict | None = None, *,
                   base: SegmentConfig | None = None, where: str = "settings") -> SegmentConfig:
    """A SegmentConfig of `modality` with `overrides` (a TOML table of its fields) applied.

    Arguments:
        modality: "mri" or "ct" (the scan's; not overridable).
        overrides: {field: value}; `register` may be a table of RegisterConfig fields.
        base: the config the overrides apply to (default: SegmentConfig's defaults).
        where: the config section named in errors.

    Returns:
        The SegmentConfig (unknown keys name the closest valid one; its own checks name a bad value).
    """
    kw = _check_settings(overrides or {}, where)
    base = base if base is not None else SegmentConfig(modality=modality)
    if isinstance(kw.get("register"), dict):
        kw["register"] = dataclasses.replace(base.register, **kw["register"])
    try:
        return dataclasses.replace(base, modality=modality, **kw)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {e}") from None


@dataclass(frozen=True, kw_only=True)
class ReferenceConfig:
    """The unperturbed head.

    Arguments:
        source: "phantom" (a synthetic head, `jaxhead.make_head`: scan and true labels),
            "scan" (a scan file, segmented by the library), "labels" (a label map file, meshed by
            the library) or "mesh" (a mesh file, `jaxhead.load_mesh`; no label map, so only the
            morph and electrode routes).
        modality, seed: the scan's modality (phantom and scan) and the phantom's subject seed.
        voxel_mm: phantom voxel size (or the size a loaded scan or label map is resampled to;
            None keeps).
        labels_path: with source = "labels", a NIfTI label map (0..4).
        scan_path: with source = "scan", a NIfTI scan (MRI magnitude or CT in HU).
        segmented: phantom: build the reference head from `jaxhead.segment` of the phantom's scan
            instead of its true labels (needed by resegment perturbations); source = "scan" is
            always segmented.
        segment: SegmentConfig fields for that segmentation (e.g. {atlas = "phantom", beta = 0.4});
            the atlas is `default_atlas` of SegmentConfig's atlas, modality and atlas_voxel_mm.
        n_elec, electrode_radius_mm, contact_impedance_ohm_m2: electrodes spread over the head.
        protocol: "adjacent" or "opposite"; current_a: injected current (A).
        sigma_s_m: conductivity per tissue (S/m), missing keys take the defaults.
        stiffening: the morph's Jacobian-based stiffening exponent (`build_morph`).
    """

    source: Literal["phantom", "scan", "labels", "mesh"] = "phantom"
    modality: Literal["mri", "ct"] = "mri"
    seed: int = 0
    voxel_mm: float | None = 4.0
    labels_path: str | None = None
    scan_path: str | None = None
    mesh_path: str | None = None
    segmented: bool = False
    segment: dict = field(default_factory=dict)
    n_elec: int = 16
    electrode_radius_mm: float = 6.0
    contact_impedance_ohm_m2: float = 0.02
    protocol: Literal["adjacent", "opposite"] = "adjacent"
    current_a: float = 1e-4
    sigma_s_m: dict = field(default_factory=dict)
    stiffening: float = 1.0

    def __post_init__(self):
        if self.source not in ("phantom", "scan", "labels", "mesh"):
            raise ValueError(f"[study.reference] source = {self.source!r}; use 'phantom', "
                             "'scan', 'labels' or 'mesh'.")
        if self.source == "scan" and not self.scan_path:
            raise ValueError('[study.reference] source = "scan" needs scan_path = "t1.nii.gz".')
        if not isinstance(self.segmented, (bool, np.bool_)):
            raise ValueError(f"[study.reference] segmented = {self.segmented!r}; use true or false.")
        if self.segmented and self.source in ("labels", "mesh"):
            raise ValueError(f"[study.reference] segmented = true, but source = {self.source!r} "
                             "has no scan to segment; use source = \"phantom\" or \"scan\".")
        if self.segment and not self.has_scan_labels:
            raise ValueError("[study.reference] segment is set, but the reference head is not "
                             "segmented; set segmented = true (phantom) or source = \"scan\", "
                             "or remove it.")
        if self.source == "mesh" and not self.mesh_path:
            raise ValueError('[study.reference] source = "mesh" needs mesh_path = "head.vtu".')
        if self.source == "labels" and not self.labels_path:
            raise ValueError('[study.reference] source = "labels" needs labels_path = "labels.nii.gz".')
        if self.modality not in ("mri", "ct"):
            raise ValueError(f"[study.reference] modality = {self.modality!r}; use 'mri' or 'ct'.")
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise ValueError(f"[study.reference] voxel_mm = {self.voxel_mm}; it must be > 0.")
        if int(self.n_elec) < 4:
            raise ValueError(f"[study.reference] n_elec = {self.n_elec}; use at least 4.")
        for name in ("electrode_radius_mm", "contact_impedance_ohm_m2", "current_a"):
            if not getattr(self, name) > 0:
                raise ValueError(f"[study.reference] {name} = {getattr(self, name)}; it must be > 0.")
        if self.protocol not in ("adjacent", "opposite"):
            raise ValueError(f"[study.reference] protocol = {self.protocol!r}; use 'adjacent' or 'opposite'.")
        for k, v in self.sigma_s_m.items():
            if k not in TISSUE_NAMES:
                raise ValueError(f"[study.reference] sigma_s_m has unknown tissue {k!r}"
                                 f"{_closest(k, TISSUE_NAMES)}; use {list(TISSUE_NAMES)}.")
            if not float(v) > 0:
                raise ValueError(f"[study.reference] sigma_s_m.{k} = {v}; conductivities are > 0 S/m.")

        if self.has_scan_labels:
            self.segment_config()  # bad keys and values fail here, before any work

    @property
    def has_scan_labels(self) -> bool:
        """The reference labels are the library's segmentation of a scan (phantom or file)."""
        return self.source == "scan" or (self.source == "phantom" and bool(self.segmented))

    def segment_config(self) -> SegmentConfig:
        """The reference segmentation's SegmentConfig."""
        return segment_config(self.modality, self.segment, where="study.reference.segment")

    def sigma(self) -> np.ndarray:
        """(4,) conductivities in S/m (BRAIN, CSF, SKULL, SCALP)."""
        d = {**dict(zip(TISSUE_NAMES, DEFAULT_SIGMA_S_M)), **self.sigma_s_m}
        return np.array([float(d[t]) for t in TISSUE_NAMES])


@dataclass(frozen=True, kw_only=True)
class PerturbationConfig:
    """One perturbation model and how many samples of it.

    Arguments:
        kind: one of `KINDS` ("grf", "dilate", "erode", "skull_scale", "csf_scale", "skull_hole",
            "skull_close", "resegment", "electrode_position").
        tissue: the interface or tissue ("brain", "csf", "skull", "scalp") for grf/dilate/erode.
        amplitude: the kind's amplitude (`KINDS` gives its meaning and unit), >= 0.
        correlation_mm: the grf's correlation length in mm.
        samples: number of samples (seeds derived from the study's seed).
        route: "morph", "remesh" or "electrodes"; default the kind's only route.
        bias_percent: resegment, MRI only: a random smooth multiplicative bias field of about
            +-bias_percent % on the scan (`jaxhead.study.perturb_scan`).
        settings: resegment only: SegmentConfig fields changed from [study.reference] segment
            for the re-segmentation (e.g. {beta = 0.2}).
    """

    kind: str
    amplitude: float
    tissue: str | None = None
    correlation_mm: float = 20.0
    samples: int = 1
    route: str | None = None
    bias_percent: float = 0.0
    settings: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"[[study.perturbations]] unknown kind {self.kind!r}"
                             f"{_closest(self.kind, KINDS)}; use one of {sorted(KINDS)}.")
        routes, meaning = KINDS[self.kind]
        if self.kind in _NEED_TISSUE:
            if self.tissue is None:
                raise ValueError(f"[[study.perturbations]] kind {self.kind!r} needs tissue = "
                                 "'brain', 'csf', 'skull' or 'scalp'.")
        if self.tissue is not None:
            t = Tissue.parse(self.tissue) if self.tissue in TISSUE_NAMES or isinstance(
                self.tissue, int) else None
            if t is None or int(t) < 1:
                raise ValueError(f"[[study.perturbations]] unknown tissue {self.tissue!r}"
                                 f"{_closest(self.tissue, TISSUE_NAMES)}; use one of "
                                 f"{list(TISSUE_NAMES)}.")
        try:
            a = float(self.amplitude)
        except (TypeError, ValueError):
            raise ValueError(f"[[study.perturbations]] amplitude = {self.amplitude!r} is not a "
                             f"number; for {self.kind!r} it is the {meaning}.") from None
        if not np.isfinite(a) or a < 0:
            raise ValueError(f"[[study.perturbations]] amplitude = {self.amplitude} for kind "
                             f"{self.kind!r}; it must be >= 0 (the {meaning}).")
        if self.kind in ("dilate", "erode") and (a != int(a) or a < 1):
            raise ValueError(f"[[study.perturbations]] {self.kind} amplitude = {self.amplitude}; "
                             "it is a whole number of voxels >= 1.")
        if self.kind in ("skull_scale",) and a == 0:
            raise ValueError("[[study.perturbations]] skull_scale amplitude = 0 removes the skull; "
                             "use a factor > 0.")
        if self.kind != "resegment" and (self.settings or self.bias_percent):
            raise ValueError(f"[[study.perturbations]] kind {self.kind!r} sets settings or "
                             "bias_percent; they belong to kind = \"resegment\" only.")
        _check_settings(self.settings, "study.perturbations.settings")
        if not (isinstance(self.bias_percent, (int, float)) and np.isfinite(self.bias_percent)
                and self.bias_percent >= 0):
            raise ValueError(f"[[study.perturbations]] bias_percent = {self.bias_percent!r}; it "
                             "must be a number >= 0 (about +-bias_percent % of bias field).")
        if not self.correlation_mm > 0:
            raise ValueError(f"[[study.perturbations]] correlation_mm = {self.correlation_mm}; it "
                             "must be > 0 mm.")
        if int(self.samples) != self.samples or self.samples < 1:
            raise ValueError(f"[[study.perturbations]] samples = {self.samples}; use a whole number >= 1.")
        if self.route is not None and self.route not in routes:
            hint = (f"unknown route{_closest(self.route, ROUTES)}" if self.route not in ROUTES
                    else f"{self.kind!r} is realised by {list(routes)} only")
            raise ValueError(f"[[study.perturbations]] route = {self.route!r}: {hint}.")

    @property
    def realised_by(self) -> str:
        return self.route or KINDS[self.kind][0][0]


@dataclass(frozen=True, kw_only=True)
class StudyConfig:
    """A segmentation-error study.

    Arguments:
        name: the study's name; out_dir: outputs go to `<out_dir>/study/`.
        seed: master seed; sample k of perturbation j gets a seed derived from (seed, j, k).
        reference: ReferenceConfig; measures: `jaxhead.study.MeasureConfig`.
        perturbations: the perturbation models (at least one).
        first_order: compute the first-order counterpart of every grf perturbation.
        retry_failed: on a rerun, run failed samples again (default: they count as finished).
    """

    name: str = "study"
    out_dir: str = "runs/study"
    seed: int = 0
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)
    measures: MeasureConfig = field(default_factory=MeasureConfig)
    perturbations: tuple[PerturbationConfig, ...] = ()
    first_order: bool = True
    retry_failed: bool = False

    def __post_init__(self):
        reseg = [p for p in self.perturbations if p.kind == "resegment"]
        rc = self.reference
        if reseg and not rc.has_scan_labels:
            fix = ("set segmented = true (the reference head is then the segmentation of the "
                   "phantom's scan, not its true labels)" if rc.source == "phantom" else
                   f"source = {rc.source!r} has no scan; use source = \"scan\" or \"phantom\"")
            raise ValueError("[[study.perturbations]] resegment segments the reference's scan again "
                             "and compares with the reference segmentation, but [study.reference] "
                             f"is not a segmented scan: {fix}.")
        for p in reseg:
            segment_config(rc.modality, p.settings, base=rc.segment_config(),
                           where="study.perturbations.settings")
            if p.bias_percent and rc.modality == "ct":
                raise ValueError(f"[[study.perturbations]] bias_percent = {p.bias_percent} with a "
                                 "CT reference: a CT has no multiplicative bias field; use 0.")
        if self.reference.source == "mesh":
            bad = [p.kind for p in self.perturbations if p.realised_by == "remesh"]
            if bad:
                raise ValueError(f"[[study.perturbations]] {sorted(set(bad))} perturb a label map "
                                 "(the re-mesh route) but [study.reference] source = \"mesh\" has "
                                 "none; use source = \"phantom\" or \"labels\", or grf / "
                                 "electrode_position perturbations.")
        if not self.perturbations:
            raise ValueError("[study] has no [[study.perturbations]]; add at least one, e.g. "
                             'kind = "grf", tissue = "csf", amplitude = 0.5, samples = 10.')

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def reference_key(self) -> str:
        """A hash of what the reference head depends on (a rerun must use the same)."""
        s = json.dumps(dataclasses.asdict(self.reference), sort_keys=True)
        return hashlib.sha256(s.encode()).hexdigest()[:16]

    def sample_key(self, j: int, k: int, seed: int) -> str:
        """A hash of everything sample k of perturbation j depends on: its perturbation's
        parameters (not its sample count), its seed, the reference head and the measures. A rerun
        reuses a finished sample only when its stored key is this one, so a result is never
        stale after a parameter changes."""
        p = {f: v for f, v in dataclasses.asdict(self.perturbations[j]).items() if f != "samples"}
        s = json.dumps({"perturbation": p, "k": int(k), "seed": int(seed),
                        "reference": dataclasses.asdict(self.reference),
                        "measures": dataclasses.asdict(self.measures)},
                       sort_keys=True, default=str)
        return hashlib.sha256(s.encode()).hexdigest()[:16]

    def first_order_key(self) -> str:
        """A hash of what the first-order task depends on: the reference, the measures and the
        grf perturbations' tissues, sds and correlation lengths."""
        grf = sorted((p.tissue, float(p.amplitude), float(p.correlation_mm))
                     for p in self.perturbations if p.kind == "grf")
        s = json.dumps({"grf": grf, "reference": dataclasses.asdict(self.reference),
                        "measures": dataclasses.asdict(self.measures)},
                       sort_keys=True, default=str)
        return hashlib.sha256(s.encode()).hexdigest()[:16]


def study_config_from_dict(d: dict) -> StudyConfig:
    """A StudyConfig from the `[study]` table's dict (as TOML parses it): every table typed and checked
    by `jaxhead._tables` (unknown keys named with the closest valid one), the same way as run configs."""
    return from_dict(StudyConfig, d, "study")


def load_study_config(path) -> StudyConfig:
    """Read a TOML file with a `[study]` section into a StudyConfig (unknown keys are errors)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"study config {str(p)!r} does not exist; pass a TOML file such as "
                         "configs/study_quick.toml.")
    with open(p, "rb") as f:
        data = tomllib.load(f)
    if "study" not in data:
        raise ValueError(f"{p} has no [study] section (top-level keys: {sorted(data)}).")
    other = set(data) - {"study"}
    if other:
        raise ValueError(f"{p} has top-level keys {sorted(other)} besides [study]; a study config "
                         "holds only the [study] section.")
    return study_config_from_dict(data["study"])
