"""What a stage reads, declared beside it: config sections and earlier stages' folders.

The declaration is the stage's fingerprint recipe: the pipeline hashes the declared config
sections, the content of every file in the declared stage folders, the files the sections name
(`path`, `*_path`, `*_mesh` keys) and the package version. A stage reading a folder it did not
declare fails (`Subject.file`), so a declaration cannot silently fall behind its stage.
"""

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class StageSpec:
    """A stage's declaration.

    Arguments:
        config: the RunConfig sections the stage reads (its own included).
        reads: the earlier stages whose folders it reads, or a function of the RunConfig that
            returns them (for a stage whose source depends on the configured stages).
        versions: (name, version) pairs of data the stage builds or reads outside the run folder
            (e.g. the cached default atlas, `jaxhead.segmentation.atlas.ATLAS_VERSION`): a new
            version reruns the stage.
    """

    config: tuple[str, ...]
    reads: tuple[str, ...] | Callable = ()
    versions: tuple[tuple[str, int | str], ...] = ()

    def reads_for(self, cfg) -> tuple[str, ...]:
        return tuple(self.reads(cfg) if callable(self.reads) else self.reads)


def stage(*, config: tuple[str, ...], reads=(), versions: dict | None = None):
    """Declare what the decorated stage function `fn(cfg, subject) -> dict` reads (`versions`: see
    StageSpec)."""

    def deco(fn):
        fn.stage_spec = StageSpec(tuple(config), reads if callable(reads) else tuple(reads),
                                  tuple(sorted((versions or {}).items())))
        return fn

    return deco


def spec_of(fn, name: str, earlier: list[str], sections: list[str]) -> StageSpec:
    """The declaration of a stage function; an undeclared one reads everything before it."""
    spec = getattr(fn, "stage_spec", None)
    if spec is None:  # e.g. a test's fake: conservative, so never stale
        return StageSpec(tuple(sections), tuple(earlier))
    return spec
