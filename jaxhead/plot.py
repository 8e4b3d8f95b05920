"""Pictures for people: label overlays on scans, mesh cut-aways, scalp potentials.  [host]"""

from pathlib import Path

import numpy as np
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from ._files import atomic_write_path
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


def plane_cut(nodes: np.ndarray, tets: np.ndarray, axis: int, offset_mm: float):
    """Polygons where the plane x[axis] = offset cuts the tets.

    Returns:
        polys: list of (k, 2) arrays (k = 3 or 4) in the plane's two other coordinates (mm).
        tet: (n_polys,) index of the tet each polygon comes from.
    """
    d = nodes[:, axis] - offset_mm
    dt = d[tets]
    cross = (dt.min(1) < 0) & (dt.max(1) > 0)
    idx = np.nonzero(cross)[0]
    other = [a for a in range(3) if a != axis]
    polys = []
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    for t in idx:
        pts = []
        for a, b in edges:
            da, db = dt[t, a], dt[t, b]
            if (da < 0) != (db < 0):
                s = da / (da - db)
                p = nodes[tets[t, a]] + s * (nodes[tets[t, b]] - nodes[tets[t, a]])
                pts.append(p[other])
        pts = np.array(pts)
        c = pts.mean(0)
        order = np.argsort(np.arctan2(pts[:, 1] - c[1], pts[:, 0] - c[0]))
        polys.append(pts[order])
    return polys, idx


def plot_mesh_cut(mesh, path: str | Path = "mesh_cut.png", *, title: str = "",
                  centre_mm=None, edges: bool = True) -> Path:
    """Three orthogonal cuts through a labelled tet mesh, tets coloured by tissue.

    Arguments:
        mesh: a `TetMesh`.
        path: the PNG to write.
        centre_mm: the point the three planes pass through (default: the mesh's centroid).
        edges: draw the tets' cut edges (shows the element size).
    """
    from matplotlib.collections import PolyCollection

    nodes, tets = np.asarray(mesh.nodes), np.asarray(mesh.tets)
    centre = nodes.mean(0) if centre_mm is None else np.asarray(centre_mm, dtype=float)
    plt, fig, axes = _figure(1, 3, size=4.2)
    names = {0: ("sagittal (x = {:.0f} mm)", "y (mm)", "z (mm)"),
             1: ("coronal (y = {:.0f} mm)", "x (mm)", "z (mm)"),
             2: ("axial (z = {:.0f} mm)", "x (mm)", "y (mm)")}
    for col, axis in enumerate((2, 1, 0)):
        ax = axes[0, col]
        polys, idx = plane_cut(nodes, tets, axis, float(centre[axis]))
        colours = [TISSUE_COLOURS[Tissue(int(mesh.labels[i]))] for i in idx]
        pc = PolyCollection(polys, facecolors=colours, edgecolors="k" if edges else "none",
                            linewidths=0.1 if edges else 0)
        ax.add_collection(pc)
        ax.autoscale()
        ax.set_aspect("equal")
        t, xl, yl = names[axis]
        ax.set_title(t.format(centre[axis]), fontsize=9)
        ax.set_xlabel(xl, fontsize=8)
        ax.set_ylabel(yl, fontsize=8)
        ax.tick_params(labelsize=7)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in TISSUE_COLOURS.values()]
    fig.legend(handles, [t.name.lower() for t in TISSUE_COLOURS], loc="lower center", ncol=4,
               fontsize=8, frameon=False)
    fig.suptitle(title or f"{mesh.n_tets} tets, {mesh.n_nodes} nodes")
    return save_figure(fig, path)


def plot_scalp_potential(nodes: np.ndarray, faces: np.ndarray, u: np.ndarray,
                         path: str | Path = "scalp_potential.png", *, electrodes_mm=None,
                         title: str = "", units: str = "mV", scale: float = 1e3) -> Path:
    """The potential on the scalp surface, seen from four sides.

    Arguments:
        nodes: (n_nodes, 3) mm; faces: (n_faces, 3) outward scalp faces; u: (n_nodes,) volts.
        electrodes_mm: optional (n_elec, 3) electrode centres drawn as dots.
        scale: factor from volts to `units` (1e3 for mV).
    """
    import matplotlib
    from matplotlib import cm, colors

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    nodes = np.asarray(nodes)
    faces = np.asarray(faces)
    val = np.asarray(u)[faces].mean(1) * scale
    lim = np.percentile(np.abs(val), 99) or 1.0
    norm = colors.TwoSlopeNorm(vmin=-lim, vcenter=0.0, vmax=lim)
    cmap = matplotlib.colormaps["RdBu_r"]
    fig = plt.figure(figsize=(13, 3.6))
    views = [("left", 0, 180), ("front", 0, 90), ("right", 0, 0), ("top", 90, -90)]
    c = nodes[np.unique(faces)].mean(0)
    r = np.abs(nodes[np.unique(faces)] - c).max()
    for i, (name, elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, 4, i + 1, projection="3d")
        coll = Poly3DCollection(nodes[faces], facecolors=cmap(norm(val)), edgecolors="none")
        ax.add_collection3d(coll)
        if electrodes_mm is not None:
            e = np.asarray(electrodes_mm)
            ax.scatter(e[:, 0], e[:, 1], e[:, 2], c="k", s=6, depthshade=False)
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(name, fontsize=9)
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=fig.axes, shrink=0.7,
                 label=f"potential ({units})")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def plot_image_cut(mesh, values, path: str | Path = "image_cut.png", *, centre_mm,
                   radius_mm: float | None = None, title: str = "", label: str = "") -> Path:
    """A per-tet image (e.g. a reconstructed conductivity change) on three cuts through `centre_mm`.

    Tets with value 0 show their tissue in grey levels (the anatomy); others a diverging colour
    map. A circle marks the true perturbation when `radius_mm` is given.
    """
    from matplotlib import colors
    from matplotlib.collections import PolyCollection
    from matplotlib.patches import Circle

    nodes, tets = np.asarray(mesh.nodes), np.asarray(mesh.tets)
    values = np.asarray(values, dtype=float)
    centre = np.asarray(centre_mm, dtype=float)
    lim = float(np.abs(values).max()) or 1.0
    norm = colors.TwoSlopeNorm(vmin=-lim, vcenter=0.0, vmax=lim)
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"]
    grey = {1: 0.85, 2: 0.65, 3: 0.95, 4: 0.75}
    plt, fig, axes = _figure(1, 3, size=4.2)
    names = {0: "sagittal", 1: "coronal", 2: "axial"}
    for col, axis in enumerate((2, 1, 0)):
        ax = axes[0, col]
        polys, idx = plane_cut(nodes, tets, axis, float(centre[axis]))
        fc = []
        for i in idx:
            v = values[i]
            fc.append(cmap(norm(v)) if v != 0 else (grey[int(mesh.labels[i])],) * 3 + (1.0,))
        ax.add_collection(PolyCollection(polys, facecolors=fc, edgecolors="none"))
        if radius_mm is not None:
            other = [a for a in range(3) if a != axis]
            ax.add_patch(Circle(centre[other], radius_mm, fill=False, ec="k", lw=1, ls="--"))
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_title(f"{names[axis]} through ({centre[0]:.0f}, {centre[1]:.0f}, {centre[2]:.0f}) mm",
                     fontsize=9)
        ax.tick_params(labelsize=7)
    sm = matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=fig.axes, shrink=0.8, label=label)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
