"""Files in and out: volumes and label maps (NIfTI, Analyze), meshes (.msh, .vtu, .mat), surfaces,
measured recordings (CSV, UCL JSON + .mat).  [host]

Every writer is atomic (`atomic_write_path`): a crash never leaves a half-written file under the
final name.
"""

from .._files import atomic_write_path as atomic_write_path
from .._files import write_csv as write_csv
from .._files import file_digest as file_digest
from .mesh import MESH_EXTENSIONS as MESH_EXTENSIONS
from .mesh import SURFACE_EXTENSIONS as SURFACE_EXTENSIONS
from .mesh import SIMNIBS_TISSUE_MAP as SIMNIBS_TISSUE_MAP
from .mesh import TISSUE_SYNONYMS as TISSUE_SYNONYMS
from .mesh import head_facing as head_facing
from .mesh import load_mesh as load_mesh
from .mesh import load_surface as load_surface
from .mesh import save_mesh as save_mesh
from .mesh import save_surface as save_surface
from .measurements import MEASUREMENT_FORMATS as MEASUREMENT_FORMATS
from .measurements import Measurements as Measurements
from .measurements import load_measurements as load_measurements
from .measurements import mat73_arrays as mat73_arrays
from .measurements import save_measurements as save_measurements
from .volume import VOLUME_EXTENSIONS as VOLUME_EXTENSIONS
from .volume import format_info as format_info
from .volume import info as info
from .volume import load_labels as load_labels
from .volume import load_volume as load_volume
from .volume import resample as resample
from .volume import save_labels as save_labels
from .volume import save_volume as save_volume

__all__ = [
    "MEASUREMENT_FORMATS", "MESH_EXTENSIONS", "Measurements", "SIMNIBS_TISSUE_MAP", "SURFACE_EXTENSIONS", "TISSUE_SYNONYMS", "VOLUME_EXTENSIONS", "atomic_write_path", "write_csv",
    "file_digest", "format_info", "head_facing", "info", "load_labels", "load_measurements", "load_mesh", "load_surface",
    "load_volume", "mat73_arrays", "resample", "save_labels", "save_measurements", "save_mesh", "save_surface", "save_volume",
]
