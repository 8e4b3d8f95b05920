"""Pictures for people: label overlays on scans, mesh cut-aways, scalp potentials.  [host]"""

from pathlib import Path

import numpy as np

from .tissue import Tissue

#: One colour per Tissue value (background transparent).
TISSUE_COLOURS = {
    Tissue.BRAIN: (0.95, 0.75, 0.65),
    Tissue.CSF: (0.30, 0.55, 0.95),
    Tissue.SKULL: (0.95, 0.95, 0.80),
    Tissue.SCALP: (0.85, 0.45, 0.35),
}


def _figure(nrows: int, ncols: int, size: float = 3.2):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(nrows, ncols, figsize=(size * ncols, size * nrows), squeeze=False)
    return plt, fig, axes


def save_figure(fig, path: str | Path) -> Path:
    """Write a matplotlib figure to PNG atomically and close it."""
    from .io import atomic_write_path
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_write_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return path


def _label_rgba(labels2d: np.ndarray, alpha: float) -> np.ndarray:
    rgba = np.zeros(labels2d.shape + (4,))
    for t, c in TISSUE_COLOURS.items():
        m = labels2d == int(t)
        rgba[m, :3] = c
        rgba[m, 3] = alpha
    return rgba


def _slices(data: np.ndarray, index: tuple[int, int, int]):
    """Axial, coronal and sagittal slices (RAS voxel axes), oriented for display."""
    i, j, k = index
    return [
        ("axial", data[:, :, k].T),
        ("coronal", data[:, j, :].T),
        ("sagittal", data[i, :, :].T),
    ]


def plot_overlay(volume, labels=None, path: str | Path = "overlay.png", *, title: str = "",
                 alpha: float = 0.35, index: tuple[int, int, int] | None = None) -> Path:
    """Three orthogonal slices of a scan, with tissue labels overlaid when given.

    Arguments:
        volume: a `Volume` (RAS-oriented; intensities windowed to the 1-99.5 percentiles).
        labels: an optional `LabelMap` on the same grid.
        path: the PNG to write.
        index: the voxel the slices pass through (default: the grid centre).
    """
    data = np.asarray(volume.data)
    if labels is not None and labels.shape != volume.shape:
        raise ValueError(
            f"`labels` has shape {labels.shape} but `volume` has {volume.shape}; "
            "overlay needs both on one grid."
        )
    if index is None:
        index = tuple(s // 2 for s in data.shape)
    lo, hi = np.percentile(data, [1, 99.5])
    ncols = 3
    nrows = 1 if labels is None else 2
    plt, fig, axes = _figure(nrows, ncols)
    aspect = volume.voxel_mm
    for col, (name, sl) in enumerate(_slices(data, index)):
        asp = {"axial": aspect[1] / aspect[0], "coronal": aspect[2] / aspect[0],
               "sagittal": aspect[2] / aspect[1]}[name]
        for row in range(nrows):
            ax = axes[row, col]
            ax.imshow(sl, cmap="gray", vmin=lo, vmax=hi, origin="lower", aspect=asp)
            if row == 1:
                lab = dict(_slices(np.asarray(labels.labels), index))[name]
                ax.imshow(_label_rgba(lab, alpha), origin="lower", aspect=asp)
            ax.set_title(name if row == 0 else f"{name} + labels", fontsize=9)
            ax.axis("off")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
