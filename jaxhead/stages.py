"""The pipeline's stages: each reads what earlier stages wrote in the run folder and writes its own.

Each stage is ``fn(cfg, subject) -> summary dict``. Only public jaxhead functions are called here;
no numerics live in this module.
"""

from .config import RunConfig
from .pipeline import Subject


def run_input(cfg: RunConfig, subject: Subject) -> dict:
    """Make the phantom (or load the scan), write scan.nii.gz (+ labels) and an overlay PNG."""
    from . import io
    from .plot import plot_overlay

    out = subject.dir("input")
    c = cfg.input
    labels = None
    if c.source == "phantom":
        from .phantom import make_head

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


def _labels_for_layers(cfg: RunConfig, subject: Subject):
    """The label map the layers stage starts from: the segmentation if it ran, else the input's."""
    from . import io

    for stage in ("segment", "input"):
        path = subject.file(stage, "labels.nii.gz")
        if (cfg.stages is None or stage in cfg.stages) and path.exists():
            return io.load_labels(path), stage
    raise ValueError(
        f"[{subject.name}] no label map to build layers from: add the 'segment' stage, or give "
        "[input] labels_path (phantoms always have labels)."
    )


def _write_text(path, text: str) -> None:
    from pathlib import Path

    from .io import atomic_write_path

    with atomic_write_path(path) as tmp:
        Path(tmp).write_text(text)


def run_layers(cfg: RunConfig, subject: Subject) -> dict:
    """Hard labels -> nested layers (closing, nesting, minimum thickness), with a per-rule report."""
    from . import io
    from .plot import plot_overlay
    from .segment.layers import make_layers_reported

    labels, source = _labels_for_layers(cfg, subject)
    layers, report = make_layers_reported(labels, cfg.layers)
    out = subject.dir("layers")
    io.save_labels(layers, out / "layers.nii.gz")
    _write_text(out / "report.txt", str(report))
    scan = io.load_volume(subject.file("input", "scan.nii.gz"))
    if scan.shape == layers.shape:
        plot_overlay(scan, layers, out / "layers.png", title=f"{subject.name}: layers")
    return {"from": source, **report.to_dict()}


def run_surfaces(cfg: RunConfig, subject: Subject) -> dict:
    """Layers -> four nested watertight surfaces (marching cubes, repair, Taubin, remeshing)."""
    from . import io
    from .surface import extract_surfaces_reported

    layers = io.load_labels(subject.file("layers", "layers.nii.gz"))
    surfaces, report = extract_surfaces_reported(layers, cfg.surfaces)
    out = subject.dir("surfaces")
    for tissue, surf in surfaces.items():
        io.save_surface(surf, out / f"{tissue.name.lower()}.stl")
    _write_text(out / "report.txt", str(report))
    return report.to_dict()


#: Stage name -> function, in pipeline order.
STAGES = {
    "input": run_input,
    "layers": run_layers,
    "surfaces": run_surfaces,
}
