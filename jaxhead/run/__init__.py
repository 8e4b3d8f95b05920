"""Runs of experiment configs: TOML config -> stages -> a resumable run folder."""

from .config import RunConfig as RunConfig
from .config import load_config as load_config
from .pipeline import run_pipeline as run_pipeline
from .stages import STAGES as STAGES
from .subject import Subject as Subject

__all__ = ["STAGES", "RunConfig", "Subject", "load_config", "run_pipeline"]
