"""jaxhead: subject-specific, differentiable finite-element head models for EIT.

The pipeline, one verb per stage (STYLE.md):

    volume, truth = make_head("mri")                     # or load_volume("scan.nii.gz")
    labels = segment(volume)                             # or truth
    layers = make_layers(labels)
    surfaces = extract_surfaces(layers)
    mesh = tetrahedralize(surfaces)
    electrodes = place_electrodes(mesh, 32)
    model = build_forward_model(mesh, electrodes)
    volts = simulate(model, default_sigma(), adjacent(32))

A stage returns its value; a stage with a report has a `*_reported` twin returning
(value, report): `segment_reported`, `make_layers_reported`, `extract_surfaces_reported`,
`tetrahedralize_reported`. Estimators return a result Module (`FitResult`, `Reconstruction`).
Arguments: the model first, then what varies (sigma), then the protocol and the data.

Subpackages, in pipeline order: `segmentation`, `geometry`, `io`, `fem`, `inverse`, `study`, `run`.
"""

from . import fem as fem
from . import geometry as geometry
from . import inverse as inverse
from . import io as io
from . import run as run
from .electrodes import DEFAULT_CONTACT_IMPEDANCE_OHM_M2 as DEFAULT_CONTACT_IMPEDANCE_OHM_M2
from .electrodes import ElectrodeConfig as ElectrodeConfig
from .electrodes import Electrodes as Electrodes
from .electrodes import electrode_refinement_points as electrode_refinement_points
from .electrodes import estimate_landmarks as estimate_landmarks
from .electrodes import layout_positions as layout_positions
from .electrodes import place_electrodes as place_electrodes
from .electrodes import spread_positions as spread_positions
from .fem import BlockCG as BlockCG
from .fem import Direct as Direct
from .fem import ForwardModel as ForwardModel
from .fem import build_forward_model as build_forward_model
from .fem import jacobian as jacobian
from .fem import potentials as potentials
from .fem import simulate as simulate
from .geometry import LayerConfig as LayerConfig
from .geometry import LayerReport as LayerReport
from .geometry import MeshConfig as MeshConfig
from .geometry import QualityReport as QualityReport
from .geometry import Surface as Surface
from .geometry import SurfaceConfig as SurfaceConfig
from .geometry import SurfaceReport as SurfaceReport
from .geometry import TetMesh as TetMesh
from .geometry import check_surface as check_surface
from .geometry import extract_surfaces as extract_surfaces
from .geometry import extract_surfaces_reported as extract_surfaces_reported
from .geometry import make_layers as make_layers
from .geometry import make_layers_reported as make_layers_reported
from .geometry import metrics as metrics
from .geometry import orient_tets as orient_tets
from .geometry import pad_labels as pad_labels
from .geometry import quality_report as quality_report
from .geometry import tet_metrics as tet_metrics
from .geometry import tetrahedralize as tetrahedralize
from .geometry import tetrahedralize_reported as tetrahedralize_reported
from .inverse import TSVD as TSVD
from .inverse import ApproximationError as ApproximationError
from .inverse import FitResult as FitResult
from .inverse import Grid as Grid
from .inverse import LineSearchGaussNewton as LineSearchGaussNewton
from .inverse import Reconstruction as Reconstruction
from .inverse import Tikhonov as Tikhonov
from .inverse import add_noise as add_noise
from .inverse import approximation_error as approximation_error
from .inverse import fit_conductivities as fit_conductivities
from .inverse import image_metrics as image_metrics
from .inverse import jacobian_grid as jacobian_grid
from .inverse import jacobian_to_grid as jacobian_to_grid
from .inverse import make_grid as make_grid
from .inverse import reconstruct as reconstruct
from .inverse import sample_conductivities as sample_conductivities
from .inverse import spherical_perturbation as spherical_perturbation
from .io import atomic_write_path as atomic_write_path
from .io import format_info as format_info
from .io import info as info
from .io import load_labels as load_labels
from .io import load_mesh as load_mesh
from .io import load_surface as load_surface
from .io import load_volume as load_volume
from .io import resample as resample
from .io import save_labels as save_labels
from .io import save_mesh as save_mesh
from .io import save_surface as save_surface
from .io import save_volume as save_volume
from .phantom import PhantomHead as PhantomHead
from .phantom import make_head as make_head
from .phantom import make_population as make_population
from .protocol import Protocol as Protocol
from .protocol import ProtocolConfig as ProtocolConfig
from .protocol import adjacent as adjacent
from .protocol import opposite as opposite
from .protocol import pair_drive as pair_drive
from .run import RunConfig as RunConfig
from .run import load_config as load_config
from .run import run_pipeline as run_pipeline
from .segmentation import Atlas as Atlas
from .segmentation import SegmentConfig as SegmentConfig
from .segmentation import Segmentation as Segmentation
from .segmentation import default_atlas as default_atlas
from .segmentation import segment as segment  # the verb; the subpackage stays importable as jaxhead.segmentation.*
from .segmentation import segment_reported as segment_reported
from .tissue import DEFAULT_SIGMA_S_M as DEFAULT_SIGMA_S_M
from .tissue import TISSUE_NAMES as TISSUE_NAMES
from .tissue import TISSUES as TISSUES
from .tissue import Tissue as Tissue
from .tissue import default_sigma as default_sigma
from .tissue import sigma_per_tet as sigma_per_tet
from .volume import LabelMap as LabelMap
from .volume import Volume as Volume

__version__ = "0.1.0"

__all__ = sorted(n for n in dir() if not n.startswith("_") and n not in ("annotations",))
