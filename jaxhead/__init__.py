"""jaxhead: subject-specific, differentiable finite-element head models for EIT.

The pipeline, one verb per stage (STYLE.md):

    volume, truth = make_head("mri")                     # or load_volume("scan.nii.gz")
    layers = make_layers(truth)                          # or segment(volume).labels
    surfaces = extract_surfaces(layers)
    mesh = tetrahedralize(surfaces)
    electrodes = place_electrodes(mesh, 32)
    model = build_forward_model(mesh, electrodes)
    volts = simulate(model, default_sigma(), adjacent(32))
"""

from .approx_error import ApproximationError, approximation_error, sample_conductivities
from .electrodes import (
    DEFAULT_CONTACT_IMPEDANCE_OHM_M2,
    ElectrodeConfig,
    Electrodes,
    electrode_refinement_points,
    estimate_landmarks,
    layout_positions,
    place_electrodes,
    spread_positions,
)
from .fem import Direct, ForwardModel, build_forward_model, jacobian, potentials, simulate
from .fit import FitResult, LineSearchGaussNewton, fit_conductivities
from .inverse import (
    TSVD,
    Reconstruction,
    Tikhonov,
    add_noise,
    image_metrics,
    jacobian_grid,
    jacobian_to_grid,
    make_grid,
    reconstruct,
    spherical_perturbation,
)
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
from .mesh import MeshConfig, TetMesh, orient_tets, tetrahedralize, tetrahedralize_reported
from .phantom import make_head, make_population
from .protocol import Protocol, ProtocolConfig, adjacent, opposite, pair_drive
from .quality import QualityReport, metrics, quality_report, tet_metrics
from .segment.layers import LayerConfig, LayerReport, make_layers, make_layers_reported, pad_labels
from .surface import (
    Surface,
    SurfaceConfig,
    SurfaceReport,
    check_surface,
    extract_surfaces,
    extract_surfaces_reported,
)
from .tissue import DEFAULT_SIGMA_S_M, TISSUE_NAMES, TISSUES, Tissue, default_sigma
from .volume import LabelMap, Volume

__version__ = "0.1.0"
