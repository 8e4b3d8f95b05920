"""jaxhead: subject-specific, differentiable finite-element head models for EIT."""

from .io import (
    atomic_write_path,
    format_info,
    info,
    load_labels,
    load_mesh,
    load_surface,
    load_volume,
    resample,
    save_labels,
    save_mesh,
    save_surface,
    save_volume,
)
from .mesh import TetMesh, orient_tets
from .surface import Surface
from .tissue import DEFAULT_SIGMA_S_M, TISSUE_NAMES, TISSUES, Tissue, default_sigma
from .volume import LabelMap, Volume

__version__ = "0.1.0"
