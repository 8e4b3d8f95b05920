"""One head in a run and its stage folders."""

from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class Subject:
    """One head in a run: its name, modality, folder and (in a cohort) its scan.

    While a stage runs, the pipeline hands it a view of the subject (`staged`) in which the
    stage's own folder is a temporary one (renamed into place when the stage succeeds) and in
    which reading a stage folder the stage did not declare is an error, so that the declared
    reads, and with them the stage's fingerprint, cannot fall behind the code.
    """

    name: str
    modality: str
    root: Path
    path: str | None = None
    stage: str | None = field(default=None, compare=False)
    staging: Path | None = field(default=None, compare=False, repr=False)
    reads: tuple[str, ...] | None = field(default=None, compare=False, repr=False)

    def staged(self, stage: str, staging: Path, reads: tuple[str, ...]) -> "Subject":
        """The view of this subject that the stage `stage` runs with (see the class docstring)."""
        return Subject(self.name, self.modality, self.root, self.path, stage, staging,
                       tuple(reads))

    def _check(self, stage: str, what: str) -> None:
        if self.stage is None or stage == self.stage:
            return
        if what == "write" or stage not in (self.reads or ()):
            # An internal invariant of the stage declarations, not a user error.
            raise RuntimeError(
                f"stage {self.stage!r} {what}s the {stage!r} folder but declares reading only "
                f"{list(self.reads or ())}; add {stage!r} to its @stage(reads=...) declaration.")

    def dir(self, stage: str) -> Path:
        """The folder a stage writes into (created); only a stage's own folder is writable."""
        self._check(stage, "write")
        if self.stage is not None and stage == self.stage and self.staging is not None:
            self.staging.mkdir(parents=True, exist_ok=True)
            return self.staging
        d = self.root / stage
        d.mkdir(parents=True, exist_ok=True)
        return d

    def file(self, stage: str, name: str) -> Path:
        """The path of a file in a stage's folder (that stage must be declared as read)."""
        self._check(stage, "read")
        if self.stage is not None and stage == self.stage and self.staging is not None:
            return self.staging / name
        return self.root / stage / name
