"""Image grids: tets grouped into cells, Jacobians summed into cells, and cell values back to tets."""




import equinox as eqx
import numpy as np
from scipy.spatial import cKDTree

from ..fem import jacobian_cells
from ..tissue import Tissue


class Grid(eqx.Module):
    """A coarse voxel grid for reconstruction: tets are grouped by the cell holding their centroid.

    Attributes:
        cell_of_tet: (n_tets,) cell index of each tet (-1 for tets not reconstructed).
        centres: (n_cells, 3) cell centres in mm (of the cells that hold tets).
        volumes: (n_cells,) tet volume in each cell, mm^3.
        cell_mm: cell edge length in mm.
    """

    cell_of_tet: np.ndarray
    centres: np.ndarray
    volumes: np.ndarray
    cell_mm: float = eqx.field(static=True)

    @property
    def n_cells(self) -> int:
        return self.centres.shape[0]


def make_grid(mesh, cell_mm: float, *, tissues=None, min_fill: float = 0.5) -> Grid:
    """Group tets into cubic cells of `cell_mm` (only tets of `tissues`, default all).

    Cells cut by the tissue's boundary hold only part of a cube; a sliver has a tiny column in
    the Jacobian, so column-normalised (NOSER) and minimum-norm images blow it up into a
    spurious peak. Cells filled below `min_fill` of a cube are therefore merged into the
    nearest cell that is filled enough (by the distance from each of their tets' centroids to
    that cell's centre), so every parameter stands for a comparable volume.

    Arguments:
        mesh: a `TetMesh`.
        cell_mm: cell edge in mm.
        tissues: the tissues to grid (names or `Tissue`), default all.
        min_fill: the smallest cell volume kept on its own, as a fraction of cell_mm^3 (0 keeps
            every cell; if no cell reaches it, none is merged).

    Returns:
        A `Grid`.
    """


    if not cell_mm > 0:
        raise ValueError(f"`cell_mm` must be > 0, got {cell_mm}.")
    if not 0 <= min_fill <= 1:
        raise ValueError(f"`min_fill` must be in [0, 1] (a fraction of a full cell), got {min_fill}.")
    cen = mesh.centroids()
    use = np.ones(mesh.n_tets, bool)
    if tissues is not None:
        use = np.isin(mesh.labels, [int(Tissue.parse(t)) for t in tissues])
    if not use.any():
        raise ValueError(f"no tet of tissues {list(tissues)} in the mesh; check `tissues`.")
    ijk = np.floor((cen - cen.min(0)) / cell_mm).astype(np.int64)
    key = (ijk[:, 0] * (ijk[:, 1].max() + 1) + ijk[:, 1]) * (ijk[:, 2].max() + 1) + ijk[:, 2]
    _, inv = np.unique(key[use], return_inverse=True)
    cell = np.full(mesh.n_tets, -1, np.int64)
    cell[use] = inv.ravel()
    vol = mesh.tet_volumes()

    def cells_of(cell):
        n = int(cell.max()) + 1
        volumes = np.bincount(cell[use], weights=vol[use], minlength=n)
        centres = np.stack([np.bincount(cell[use], weights=vol[use] * cen[use, d], minlength=n)
                            for d in range(3)], axis=1) / volumes[:, None]
        return volumes, centres

    volumes, centres = cells_of(cell)
    full = volumes >= min_fill * cell_mm**3
    if full.any() and not full.all():
        big = np.flatnonzero(full)
        move = use & ~full[np.maximum(cell, 0)]
        _, nearest = cKDTree(centres[big]).query(cen[move])
        cell[move] = big[nearest]
        _, cell[use] = np.unique(cell[use], return_inverse=True)  # renumber 0..n-1
        volumes, centres = cells_of(cell)
    return Grid(cell, centres, volumes, float(cell_mm))


def jacobian_to_grid(J, grid: Grid) -> np.ndarray:
    """Sum the per-tet Jacobian columns into grid cells: (n_rows, n_tets) -> (n_rows, n_cells).

    A cell's parameter is a uniform conductivity change over its tets, so its column is the sum
    of theirs (chain rule).
    """
    J = np.asarray(J)
    if J.shape[1] != grid.cell_of_tet.shape[0]:
        raise ValueError(f"`J` has {J.shape[1]} columns but the grid was made for "
                         f"{grid.cell_of_tet.shape[0]} tets.")
    use = grid.cell_of_tet >= 0
    out = np.zeros((J.shape[0], grid.n_cells), dtype=np.float64)
    np.add.at(out.T, grid.cell_of_tet[use], J[:, use].T.astype(np.float64))
    return out


def grid_to_tets(x_cells, grid: Grid) -> np.ndarray:
    """Spread a cell image back onto the tets (0 for tets outside the grid)."""
    x = np.asarray(x_cells)
    out = np.zeros(grid.cell_of_tet.shape[0], dtype=x.dtype)
    use = grid.cell_of_tet >= 0
    out[use] = x[grid.cell_of_tet[use]]
    return out


# --- image metrics ------------------------------------------------------------------------------


def jacobian_grid(model, sigma, protocol, grid: Grid, *, tile_tets: int = 8192,
                  return_volts: bool = False):
    """The Jacobian summed into the grid's cells, (n_rows, n_cells), without the per-tet matrix.

    Equal to `jacobian_to_grid(jacobian(model, sigma, protocol), grid)`; see
    `jaxhead.fem.jacobian_cells` for the memory this saves.

    Arguments:
        model: a `ForwardModel`; sigma: (4,) or (n_tets,) conductivity in S/m.
        protocol: the `Protocol` (concrete rows).
        grid: a `Grid` from `make_grid(mesh, ...)` of the model's mesh.
        tile_tets: tets per tile.
        return_volts: also return the (n_rows,) voltages at sigma (from the same solves).

    Returns:
        (n_rows, n_cells) NumPy array in V / (S/m) (and the voltages with return_volts).
    """
    if grid.cell_of_tet.shape != (model.n_tets,):
        raise ValueError(f"`grid` was made for {grid.cell_of_tet.shape[0]} tets but the model "
                         f"has {model.n_tets}; make the grid from the model's mesh.")
    return jacobian_cells(model, sigma, protocol, grid.cell_of_tet, grid.n_cells,
                          tile_tets=tile_tets, return_volts=return_volts)
