"""From a label map to a four-tissue tet mesh: layers, surfaces, tetrahedralisation, improvement, quality.  [host]

Pipeline order: `make_layers` (closing, nesting, minimum thickness) -> `extract_surfaces`
(watertight nested surfaces) -> `tetrahedralize` (labelled tets, improved to the seed paper's
Table 2 limits) -> `quality_report` (Verdict metrics).
"""

from .improve import improve_mesh as improve_mesh
from .layers import LayerConfig as LayerConfig
from .layers import LayerReport as LayerReport
from .layers import make_layers as make_layers
from .layers import make_layers_reported as make_layers_reported
from .layers import pad_labels as pad_labels
from .quality import QualityReport as QualityReport
from .quality import metrics as metrics
from .quality import outside_range as outside_range
from .quality import quality_report as quality_report
from .quality import tet_metrics as tet_metrics
from .surface import Surface as Surface
from .surface import SurfaceConfig as SurfaceConfig
from .surface import SurfaceReport as SurfaceReport
from .surface import check_surface as check_surface
from .surface import extract_surfaces as extract_surfaces
from .surface import extract_surfaces_reported as extract_surfaces_reported
from .tetmesh import TetMesh as TetMesh
from .tetmesh import face_adjacency as face_adjacency
from .tetmesh import orient_tets as orient_tets
from .tetmesh import enclosed_volume as enclosed_volume
from .tetmesh import signed_volumes as signed_volumes
from .tetrahedralize import MeshConfig as MeshConfig
from .tetrahedralize import MeshReport as MeshReport
from .tetrahedralize import tetrahedralize as tetrahedralize
from .tetrahedralize import tetrahedralize_reported as tetrahedralize_reported

__all__ = [
    "LayerConfig", "LayerReport", "MeshConfig", "MeshReport", "QualityReport", "Surface",
    "SurfaceConfig", "SurfaceReport", "TetMesh", "check_surface", "enclosed_volume", "extract_surfaces",
    "extract_surfaces_reported", "face_adjacency", "improve_mesh", "make_layers",
    "make_layers_reported", "metrics", "orient_tets", "outside_range", "pad_labels",
    "quality_report", "signed_volumes", "tet_metrics", "tetrahedralize", "tetrahedralize_reported",
]
