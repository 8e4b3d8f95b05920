"""From voltages back to conductivity: difference imaging (TSVD, Tikhonov) on grids, image metrics,
noise, and fitting tissue conductivities (optimistix), with an approximation-error model.  [jax]"""

from .approx_error import ApproximationError as ApproximationError
from .approx_error import approximation_error as approximation_error
from .approx_error import sample_conductivities as sample_conductivities
from .fit import FitResult as FitResult
from .fit import LineSearchGaussNewton as LineSearchGaussNewton
from .fit import fit_conductivities as fit_conductivities
from .fit import fit_conductivities_batch as fit_conductivities_batch
from .fit import Spectrum as Spectrum
from .fit import fit_spectrum as fit_spectrum
from .grid import Grid as Grid
from .grid import grid_to_tets as grid_to_tets
from .grid import jacobian_grid as jacobian_grid
from .grid import jacobian_to_grid as jacobian_to_grid
from .grid import make_grid as make_grid
from .imaging import SVD as SVD
from .imaging import TSVD as TSVD
from .imaging import Reconstruction as Reconstruction
from .imaging import Tikhonov as Tikhonov
from .imaging import reconstruct as reconstruct
from .imaging import reconstruct_batch as reconstruct_batch
from .imaging import svd as svd
from .metrics import ImageMetrics as ImageMetrics
from .metrics import image_metrics as image_metrics
from .noise import add_noise as add_noise
from .noise import noise_std as noise_std
from .perturbation import perturbation_mask as perturbation_mask
from .perturbation import simulate_difference as simulate_difference
from .perturbation import spherical_perturbation as spherical_perturbation

__all__ = [
    "SVD", "TSVD", "ApproximationError", "FitResult", "Grid", "ImageMetrics", "LineSearchGaussNewton",
    "Reconstruction", "Tikhonov", "add_noise", "approximation_error", "fit_conductivities",
    "fit_conductivities_batch", "fit_spectrum", "Spectrum", "grid_to_tets", "image_metrics", "jacobian_grid", "jacobian_to_grid",
    "make_grid", "noise_std", "perturbation_mask", "reconstruct", "reconstruct_batch",
    "sample_conductivities", "simulate_difference", "spherical_perturbation", "svd",
]
