"""Runs of experiment configs: TOML config -> stages -> a resumable run folder."""

from .config import RunConfig as RunConfig
from .config import load_config as load_config
from .declare import stage as stage
from .lock import RunLockedError as RunLockedError
from .pipeline import StageError as StageError
from .pipeline import run_pipeline as run_pipeline
from .report import write_report as write_report
from .stages import STAGES as STAGES
from .subject import Subject as Subject

__all__ = ["STAGES", "RunConfig", "RunLockedError", "StageError", "Subject", "load_config",
           "run_pipeline", "stage", "write_report"]
