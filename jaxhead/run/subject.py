"""One head in a run and its stage folders."""

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Subject:
    """One head in a run: its name, modality and folder."""

    name: str
    modality: str
    root: Path

    def dir(self, stage: str) -> Path:
        d = self.root / stage
        d.mkdir(parents=True, exist_ok=True)
        return d

    def file(self, stage: str, name: str) -> Path:
        return self.root / stage / name
