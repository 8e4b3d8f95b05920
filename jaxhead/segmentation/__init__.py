"""Segmentation of head MRI/CT: atlas, registration, EM with MRF and bias field, `segment`.

(The post-processing into nested layers is `jaxhead.geometry.make_layers`.)
"""

from .atlas import Atlas, build_atlas, cache_dir, default_atlas
from .em import EMOptions, EMResult, MixtureParams, fit_mixture, infer_posteriors
from .mrf import mean_field, neighbour_sum, potts_energy
from .register import (
    AffineTransform,
    BSplineTransform,
    RegisterConfig,
    affine_register,
    bspline_register,
    register,
    resample,
    warp_volume,
)
from .segment import Segmentation, SegmentConfig, classify, register_atlas, segment

__all__ = [
    "AffineTransform", "Atlas", "BSplineTransform", "EMOptions", "EMResult", "MixtureParams",
    "RegisterConfig", "SegmentConfig", "Segmentation", "affine_register", "bspline_register",
    "build_atlas", "cache_dir", "classify", "default_atlas", "fit_mixture", "infer_posteriors", "mean_field",
    "neighbour_sum", "potts_energy", "register", "register_atlas", "resample", "segment", "warp_volume",
]
