"""Runs the configured stages into a run folder, resumable stage by stage.

Layout: ``<run_dir>/<subject>/<stage>/`` holds each stage's files and a ``done.json`` marker with the
hash of the configuration that produced it (chained through the earlier stages). A stage whose
marker matches is skipped on the next run; ``force=True`` reruns everything. Stages talk to each other
only through the files in the run folder, so any stage can be resumed from disk.
"""

import dataclasses
import hashlib
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

from .._files import atomic_write_path
from .config import RunConfig
from .stages import STAGES
from .subject import Subject

log = logging.getLogger("jaxhead")


StageFn = Callable[[RunConfig, Subject], dict]


def _jsonable(obj):
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(getattr(k, "name", k)).lower(): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj


#: Config sections a stage reads besides its own (the mesh is refined under the electrodes;
#: the inverse stage rebuilds the forward model, so it reads what the forward stage reads).
STAGE_READS = {"mesh": ("electrodes",), "forward": ("electrodes", "protocol"),
               "inverse": ("forward", "electrodes", "protocol")}


def _file_digests(obj) -> dict[str, str]:
    """sha256 of every existing file a `*_path` (or `path`) field names, by path."""
    out = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            if (k == "path" or k.endswith("_path")) and isinstance(v, str) and Path(v).is_file():
                h = hashlib.sha256()
                with open(v, "rb") as f:
                    for block in iter(lambda: f.read(1 << 20), b""):
                        h.update(block)
                out[v] = h.hexdigest()
            else:
                out.update(_file_digests(v))
    elif isinstance(obj, list):
        for v in obj:
            out.update(_file_digests(v))
    return out


def stage_hash(cfg: RunConfig, stage: str, previous: str) -> str:
    """Hash of the config sections a stage reads, chained with the previous stage's hash.

    Files the sections name (`path`, `labels_path`, `measured_path`) enter by content, so a
    changed file reruns the stage that reads it (and every later one).
    """
    sections = _jsonable([getattr(cfg, name, None) for name in (stage, *STAGE_READS.get(stage, ()))])
    digests = _file_digests(sections)  # left out when empty: hashes of file-free stages stay
    payload = json.dumps([previous, stage, sections] + ([digests] if digests else []),
                         sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _write_json(path: Path, data: dict) -> None:

    with atomic_write_path(path) as tmp:
        Path(tmp).write_text(json.dumps(_jsonable(data), indent=2, default=str))


def _read_done(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def subjects(cfg: RunConfig) -> list[Subject]:
    """The subjects a run processes (one per phantom modality, or the one input file)."""
    root = cfg.run_dir
    if cfg.input.source == "phantom":
        return [Subject(m, m, root / m) for m in cfg.input.modalities]
    return [Subject("subject", cfg.input.modality, root / "subject")]


def run_pipeline(cfg: RunConfig, *, force: bool = False, stages: dict[str, StageFn] | None = None,
                 progress: Callable[[str], None] | None = None) -> dict:
    """Run every configured stage for every subject; returns {subject: {stage: summary}}.

    Arguments:
        cfg: the run configuration.
        force: rerun stages even when their outputs are up to date.
        stages: the stage functions by name, in pipeline order (default: `jaxhead.run.stages.STAGES`).
        progress: called with one line of text as stages start and finish (default: logging).
    """

    stages = STAGES if stages is None else stages
    names = list(stages) if cfg.stages is None else list(cfg.stages)
    unknown = [n for n in names if n not in stages]
    if unknown:
        raise ValueError(
            f"unknown stage(s) {unknown} in `stages`; available, in order: {list(stages)}."
        )
    order = [n for n in stages if n in names]
    if order != names:
        raise ValueError(f"`stages` must follow pipeline order {list(stages)}; got {names}.")
    say = progress or log.info
    cfg.run_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict] = {}
    for subject in subjects(cfg):
        previous = ""
        results[subject.name] = {}
        dirty = force
        for name in order:
            h = stage_hash(cfg, name, previous)
            previous = h
            marker = subject.root / name / "done.json"
            done = _read_done(marker)
            if not dirty and done is not None and done.get("hash") == h:
                say(f"[{subject.name}] {name}: up to date ({done.get('seconds', 0):.1f} s before), skipped")
                results[subject.name][name] = done.get("summary", {})
                continue
            dirty = True  # every later stage reruns too
            marker.unlink(missing_ok=True)
            say(f"[{subject.name}] {name}: running ...")
            t0 = time.perf_counter()
            summary = stages[name](cfg, subject) or {}
            seconds = time.perf_counter() - t0
            _write_json(marker, {"stage": name, "hash": h, "seconds": seconds, "summary": summary})
            say(f"[{subject.name}] {name}: done in {seconds:.1f} s")
            results[subject.name][name] = summary
    _write_json(cfg.run_dir / "summary.json", results)
    return results
