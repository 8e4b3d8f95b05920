"""Segmentation of head MRI/CT: atlas, registration, EM with MRF and bias field, `segment`
(and `segment_reported`, which returns the fitted model too).

(The post-processing into nested layers is `jaxhead.geometry.make_layers`.)
"""

from .atlas import Atlas, anatomy_atlas, build_atlas, cache_dir, default_atlas
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
from .segment import (
    Segmentation,
    SegmentConfig,
    check_label_map,
    check_orientation,
    check_registration,
    classify,
    config_atlas,
    dice_scores,
    register_atlas,
    registration_summary,
    segment,
    segment_reported,
)
from .templates import Anatomy, ants_anatomy, mni152_anatomy, rasterise, read_jnifti, render

__all__ = [
    "AffineTransform", "Anatomy", "Atlas", "anatomy_atlas", "ants_anatomy", "check_label_map", "check_orientation",
    "check_registration", "config_atlas", "dice_scores", "mni152_anatomy", "rasterise", "read_jnifti", "registration_summary",
    "render", "BSplineTransform", "EMOptions", "EMResult", "MixtureParams",
    "RegisterConfig", "SegmentConfig", "Segmentation", "affine_register", "bspline_register",
    "build_atlas", "cache_dir", "classify", "default_atlas", "fit_mixture", "infer_posteriors", "mean_field",
    "neighbour_sum", "potts_energy", "register", "register_atlas", "resample", "segment", "segment_reported", "warp_volume",
]
