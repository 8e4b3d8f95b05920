"""What a sample measures against the unperturbed reference head.  [host + jax]

For a perturbed head (morphed nodes, or a re-meshed model) with the reference's protocol:
- voltage change: ||V_p - V_r|| / ||V_r|| and the RMS of (V_p - V_r) / noise_sd, noise_sd the
  seed paper's 0.5 % per channel, floored at 3 % of the RMS standing voltage so channels with a
  near-zero standing voltage are not trusted beyond the model (as `jaxhead.run` whitens);
- difference imaging: a spherical brain perturbation (a stroke-like blob) simulated on the
  perturbed head, reconstructed with the *reference* head's Jacobian on a grid (TSVD, noise
  weighted, half-NOSER, k fixed at the reference's GCV choice so every sample is regularised
  alike): localisation error, correlation with the reference head's own image, fraction of
  image energy outside the true ball;
- conductivity fit on the reference head to the perturbed head's (noise-free) data: bias per
  tissue in % and whether the fit's 95 % interval (+-1.96 standard errors at 0.5 % noise)
  covers the truth.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ..fem import ForwardModel, simulate
from ..geometry import TetMesh
from ..inverse import (
    TSVD,
    Grid,
    add_noise,
    fit_conductivities,
    image_metrics,
    jacobian_grid,
    make_grid,
    noise_std,
    perturbation_mask,
    reconstruct,
    svd,
)
from ..tissue import TISSUE_NAMES

#: Columns a sample's measures add to samples.csv (in this order).
MEASURE_COLUMNS = (
    "rel_voltage_change", "voltage_change_over_noise", "localisation_error_mm",
    "image_correlation", "energy_outside", *(f"sigma_bias_percent_{t}" for t in TISSUE_NAMES),
    *(f"sigma_covered_{t}" for t in TISSUE_NAMES),
)


@dataclasses.dataclass(frozen=True, kw_only=True)
class MeasureConfig:
    """Settings of the measures (units in the names).

    Attributes:
        noise_percent: measurement noise in % per channel (the seed paper's 0.5).
        noise_floor: floor of the noise reference, fraction of the RMS standing voltage.
        cell_mm: reconstruction grid cell (brain only).
        blob_radius_mm, blob_rel_change: the brain perturbation imaged in every sample.
        blob_centre_mm: its centre; None puts it 40 % of the way from the brain's centroid to its
            top (as `jaxhead run`'s inverse stage).
        imaging, fit: compute those measures (each costs solves).
        seed: noise seed of the reference image's k choice.
    """

    noise_percent: float = 0.5
    noise_floor: float = 0.03
    cell_mm: float = 12.0
    blob_radius_mm: float = 20.0
    blob_rel_change: float = 0.2
    blob_centre_mm: tuple[float, float, float] | None = None
    imaging: bool = True
    fit: bool = True
    seed: int = 0

    def __post_init__(self):
        for name in ("noise_percent", "cell_mm", "blob_radius_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"measures.{name} = {v!r}; it must be a number > 0.")
        if not self.blob_rel_change > -1:
            raise ValueError(f"measures.blob_rel_change = {self.blob_rel_change}; it must be > -1.")


class Reference:
    """The unperturbed head and everything the measures compare with (built once per worker).

    Attributes:
        mesh, model, protocol, sigma: the reference head (sigma (4,) S/m).
        volts: (n_rows,) reference voltages; noise_sd: (n_rows,) noise standard deviations (V).
        grid, J_grid: brain grid and the reference Jacobian summed into it (n_rows, n_cells).
        centre_mm: blob centre; k: TSVD truncation; image: the reference head's own image.
    """

    def __init__(self, mesh: TetMesh, model: ForwardModel, protocol, sigma,
                 cfg: MeasureConfig = MeasureConfig()):
        self.mesh, self.model, self.protocol, self.cfg = mesh, model, protocol, cfg
        self.sigma = np.asarray(sigma, dtype=np.float64)
        self.volts = np.asarray(simulate(model, self.sigma, protocol))
        self.noise_sd = noise_std(self.volts, cfg.noise_percent, floor=cfg.noise_floor)
        self.centre_mm = (blob_centre(mesh) if cfg.blob_centre_mm is None
                          else np.asarray(cfg.blob_centre_mm, dtype=np.float64))
        if cfg.imaging:
            self.grid = make_grid(mesh, cfg.cell_mm, tissues=["brain"])
            self.J_grid = jacobian_grid(model, self.sigma, protocol, self.grid)
            self.method = TSVD(noise_weighted=True, normalise=0.5)
            self.dec = svd(self.J_grid / self.noise_sd[:, None], normalise=0.5)
            dv = blob_data(mesh, model, self.sigma, protocol, self.centre_mm, cfg) - self.volts
            noisy = add_noise(dv, cfg.noise_percent, seed=cfg.seed, reference=self.volts)
            self.k = int(round(reconstruct(None, noisy, self.method, noise_std=self.noise_sd,
                                           decomposition=self.dec).k))
            self.image = self.reconstruct(dv)
            self.metrics = image_metrics(self.image, self.grid, self.centre_mm,
                                         cfg.blob_radius_mm, sign=np.sign(cfg.blob_rel_change))

    def reconstruct(self, dv) -> np.ndarray:
        """Image (n_cells,) of a voltage change with the reference Jacobian and fixed k."""
        m = TSVD(k=self.k, noise_weighted=True, normalise=0.5)
        return np.asarray(reconstruct(None, dv, m, noise_std=self.noise_sd,
                                      decomposition=self.dec).image)


def blob_centre(mesh: TetMesh) -> np.ndarray:
    """40 % of the way up from the brain's volume centroid to its top (mm)."""
    brain = mesh.labels == 1
    cen, vol = mesh.centroids()[brain], mesh.tet_volumes()[brain]
    middle = (cen * vol[:, None]).sum(0) / vol.sum()
    return middle + 0.4 * np.array([0.0, 0.0, cen[:, 2].max() - middle[2]])


def blob_sigma(mesh: TetMesh, sigma, centre_mm, cfg: MeasureConfig) -> np.ndarray:
    """(n_tets,) conductivity with the brain blob (tets whose centroid is in the ball)."""
    s = np.asarray(sigma, dtype=np.float64)[mesh.labels - 1]
    inside = perturbation_mask(mesh, centre_mm, cfg.blob_radius_mm, tissue="brain")
    if not inside.any():
        raise ValueError(f"no brain tet within {cfg.blob_radius_mm} mm of {list(centre_mm)}; "
                         "move measures.blob_centre_mm or enlarge blob_radius_mm.")
    s[inside] *= 1.0 + cfg.blob_rel_change
    return s


def blob_data(mesh, model, sigma, protocol, centre_mm, cfg, *, nodes=None) -> np.ndarray:
    """Voltages (n_rows,) with the blob; for a morph pass the reference mesh and `nodes`."""
    return np.asarray(simulate(model, blob_sigma(mesh, sigma, centre_mm, cfg), protocol,
                               nodes=nodes))


def _corr(a, b, w) -> float:
    a, b = a - np.average(a, weights=w), b - np.average(b, weights=w)
    den = np.sqrt(np.sum(w * a * a) * np.sum(w * b * b))
    return float(np.sum(w * a * b) / den) if den > 0 else float("nan")


def measure(ref: Reference, volts, blob_volts=None) -> dict:
    """The measures of one perturbed head.

    Arguments:
        ref: the Reference.
        volts: (n_rows,) perturbed head's voltages (V) at the reference conductivities.
        blob_volts: (n_rows,) its voltages with the brain blob (needed when imaging is on).

    Returns:
        {column: value} for `MEASURE_COLUMNS` (NaN where a measure is off).
    """
    cfg = ref.cfg
    v = np.asarray(volts, dtype=np.float64)
    dv = v - ref.volts
    out = dict.fromkeys(MEASURE_COLUMNS, float("nan"))
    out["rel_voltage_change"] = float(np.linalg.norm(dv) / np.linalg.norm(ref.volts))
    out["voltage_change_over_noise"] = float(np.sqrt(np.mean((dv / ref.noise_sd) ** 2)))
    if cfg.imaging:
        if blob_volts is None:
            raise ValueError("imaging is on: pass the perturbed head's `blob_volts`.")
        x = ref.reconstruct(np.asarray(blob_volts) - v)
        g: Grid = ref.grid
        sign = np.sign(cfg.blob_rel_change)
        try:
            m = image_metrics(x, g, ref.centre_mm, cfg.blob_radius_mm, sign=sign)
            out["localisation_error_mm"] = m.localisation_error_mm
        except ValueError:  # no value of the blob's sign: nothing to localise
            pass
        out["image_correlation"] = _corr(x, ref.image, g.volumes)
        outside = np.linalg.norm(g.centres - ref.centre_mm, axis=1) > cfg.blob_radius_mm
        e = g.volumes * x * x
        out["energy_outside"] = float(e[outside].sum() / e.sum())
    if cfg.fit:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # ill-conditioning: read the SEs
            fit = fit_conductivities(ref.model, ref.protocol, v, init=ref.sigma,
                                     noise_std=ref.noise_sd, throw=False)
        for name, est, se in zip(fit.fitted, fit.estimates, fit.std_error):
            true = ref.sigma[TISSUE_NAMES.index(name)]
            out[f"sigma_bias_percent_{name}"] = float(100.0 * (est / true - 1.0))
            out[f"sigma_covered_{name}"] = float(abs(est - true) <= 1.96 * se)
    return out
