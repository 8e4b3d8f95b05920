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


#: Stage name -> function, in pipeline order.
STAGES = {
    "input": run_input,
}
