"""Segmentation-error studies: perturbed heads (morphed or re-meshed), what each changes, the
first-order counterpart, and a Dask engine that runs many samples.  [host + jax]"""

from .grf import grf_covariance as grf_covariance
from .grf import sample_grf as sample_grf
from .morph import Interface as Interface
from .morph import Morph as Morph
from .morph import MorphError as MorphError
from .morph import MorphQuality as MorphQuality
from .morph import build_morph as build_morph
from .morph import interface_surfaces as interface_surfaces
from .morph import laplacian as laplacian
from .morph import morph_nodes as morph_nodes
from .morph import morph_quality as morph_quality

__all__ = [
    "Interface", "Morph", "MorphError", "MorphQuality", "build_morph", "grf_covariance",
    "interface_surfaces", "laplacian", "morph_nodes", "morph_quality", "sample_grf",
]
