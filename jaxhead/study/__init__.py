"""Segmentation-error studies: perturbed heads (morphed or re-meshed), what each changes, the
first-order counterpart, and a Dask engine that runs many samples.  [host + jax]"""

from .config import KINDS as KINDS
from .config import PerturbationConfig as PerturbationConfig
from .config import ReferenceConfig as ReferenceConfig
from .config import StudyConfig as StudyConfig
from .config import load_study_config as load_study_config
from .config import segment_config as segment_config
from .config import study_config_from_dict as study_config_from_dict
from .engine import COLUMNS as COLUMNS
from .engine import DICE_COLUMNS as DICE_COLUMNS
from .engine import connect as connect
from .engine import expand_samples as expand_samples
from .engine import finished_samples as finished_samples
from .engine import load_reference as load_reference
from .engine import load_reference_scan as load_reference_scan
from .engine import prepare_reference as prepare_reference
from .engine import run_study as run_study
from .engine import summarise as summarise
from .first_order import displacement_sensitivity as displacement_sensitivity
from .first_order import first_order_summary as first_order_summary
from .first_order import fit_map as fit_map
from .first_order import linear_prediction as linear_prediction
from .first_order import node_gradients as node_gradients
from .first_order import second_order_prediction as second_order_prediction
from .first_order import taylor_terms as taylor_terms
from .first_order import voltage_covariance as voltage_covariance
from .grf import grf_covariance as grf_covariance
from .grf import sample_grf as sample_grf
from .measures import MEASURE_COLUMNS as MEASURE_COLUMNS
from .measures import MeasureConfig as MeasureConfig
from .measures import Reference as Reference
from .measures import blob_centre as blob_centre
from .measures import blob_data as blob_data
from .measures import blob_sigma as blob_sigma
from .measures import measure as measure
from .morph import Interface as Interface
from .morph import Morph as Morph
from .morph import MorphError as MorphError
from .morph import MorphQuality as MorphQuality
from .morph import build_morph as build_morph
from .morph import interface_surfaces as interface_surfaces
from .morph import laplacian as laplacian
from .morph import morph_nodes as morph_nodes
from .morph import morph_quality as morph_quality
from .perturb import LABEL_KINDS as LABEL_KINDS
from .perturb import dilate_erode as dilate_erode
from .perturb import jitter_electrodes as jitter_electrodes
from .perturb import perturb_labels as perturb_labels
from .perturb import scale_thickness as scale_thickness
from .perturb import skull_close as skull_close
from .perturb import skull_hole as skull_hole
from .resegmentation import perturb_scan as perturb_scan
from .resegmentation import resegment as resegment
from .resegmentation import robust_range as robust_range

__all__ = sorted(n for n in dir() if not n.startswith("_") and n not in ("annotations",) and n not in ("grf", "morph", "measures", "first_order", "perturb", "config", "engine", "resegmentation"))
