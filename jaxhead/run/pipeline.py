"""Runs the configured stages into a run folder, resumable stage by stage.

Layout: ``<run_dir>/<subject>/<stage>/`` holds each stage's files and a ``done.json`` with the
stage's fingerprint and the sha256 of every file it wrote. A stage is up to date, and skipped,
only when its fingerprint is unchanged and its outputs are all there, unchanged. The fingerprint
covers the config sections the stage reads, the content of every file in the earlier stage
folders it reads, the files its config names, and the jaxhead version (`declare.py`); so a
re-meshed head reruns every stage that reads the mesh, and a deleted or edited output reruns its
stage. Each rerun says why.

A stage writes into a hidden temporary folder beside its own; on success its done.json is
written there and the folder replaces the stage folder by rename. A failed or killed stage leaves
the previous complete folder (or, killed between the two renames, none), never a mix. One process
at a time works in a run folder (`lock.py`).
"""

import contextlib
import dataclasses
import datetime
import hashlib
import json
import logging
import os
import secrets
import shutil
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

from .._files import atomic_write_path, file_digest
from .config import RunConfig
from .declare import StageSpec, spec_of
from .lock import run_lock
from .progress import heartbeat
from .report import write_report
from .stages import STAGES
from .subject import Subject

log = logging.getLogger("jaxhead")


StageFn = Callable[[RunConfig, Subject], dict]

DONE = "done.json"


class StageError(ValueError):
    """A stage failed on its input or environment; the message names subject, stage and cause."""


def package_version() -> str:
    """The installed jaxhead version (part of every stage's fingerprint)."""
    try:
        return metadata.version("jaxhead")
    except metadata.PackageNotFoundError:  # running from a source tree that is not installed
        return "unknown"


def _jsonable(obj):
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(getattr(k, "name", k)).lower(): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return obj


# --- digests -------------------------------------------------------------------------------------

_DIGESTS: dict[tuple, str] = {}


def _digest(path: Path) -> str:
    """sha256 of a file, cached by (path, inode, size, mtime) within this process."""
    st = path.stat()
    key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        _DIGESTS[key] = file_digest(path)
    return _DIGESTS[key]


def folder_digests(folder: Path) -> dict[str, str]:
    """sha256 of every file under a stage folder by relative path (done.json, hidden names out)."""
    out = {}
    if not folder.is_dir():
        return out
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder)
        if p.is_file() and rel.as_posix() != DONE and not any(s.startswith(".") for s in rel.parts):
            out[rel.as_posix()] = _digest(p)
    return out


def _named_files(obj, out: dict) -> dict:
    """Digests of the files config keys `path`, `*_path` and `*_mesh` name (None: missing)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if (k == "path" or k.endswith(("_path", "_mesh"))) and isinstance(v, str):
                out[v] = _digest(Path(v)) if Path(v).is_file() else None
            else:
                _named_files(v, out)
    elif isinstance(obj, list):
        for v in obj:
            _named_files(v, out)
    return out


def fingerprint(cfg: RunConfig, subject: Subject, name: str, spec: StageSpec) -> dict:
    """What a stage's outputs depend on: version, config sections, input files (by content)."""
    config = {s: _jsonable(getattr(cfg, s)) for s in spec.config}
    inputs = {}
    for s in spec.reads_for(cfg):
        inputs.update({f"{s}/{k}": v for k, v in folder_digests(subject.root / s).items()})
    return {"version": package_version(), "config": config, "inputs": inputs,
            "files": _named_files(config, {})}


def _hash(fp: dict) -> str:
    return hashlib.sha256(json.dumps(fp, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _flat(d, prefix=""):
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: d}


def _changes(old: dict, new: dict, what: str, limit: int = 3) -> list[str]:
    a, b = _flat(old or {}), _flat(new or {})
    out = []
    for k in sorted(set(a) | set(b)):
        if k not in b:
            out.append(f"{what} {k} gone")
        elif k not in a:
            out.append(f"{what} {k} new")
        elif a[k] != b[k]:
            out.append(f"{what} {k} changed" + (f" ({a[k]!r} -> {b[k]!r})" if what == "config"
                                               else ""))
    if len(out) > limit:
        out = out[:limit] + [f"{len(out) - limit} more"]
    return out


def why_stale(done: dict | None, fp: dict, folder: Path) -> str | None:
    """Why a stage folder is not up to date for fingerprint `fp` (None: it is)."""
    if done is None:
        return "no complete earlier run"
    old = done.get("fingerprint")
    if not isinstance(old, dict) or "outputs" not in done:
        return "done.json from an older jaxhead (no fingerprint)"
    if old.get("version") != fp["version"]:
        return f"jaxhead version {old.get('version')} -> {fp['version']}"
    reasons = (_changes(old.get("config"), fp["config"], "config")
               + _changes(old.get("inputs"), fp["inputs"], "input")
               + _changes(old.get("files"), fp["files"], "file"))
    if reasons:
        return "; ".join(reasons)
    have = folder_digests(folder)
    bad = []
    for rel, digest in done["outputs"].items():
        if rel not in have:
            bad.append(f"output {rel} missing")
        elif have[rel] != digest:
            bad.append(f"output {rel} changed")
    if bad:
        return "; ".join(bad[:3] + ([f"{len(bad) - 3} more"] if len(bad) > 3 else []))
    return None


# --- folders -------------------------------------------------------------------------------------


def _write_json(path: Path, data: dict) -> None:
    with atomic_write_path(path) as tmp:
        Path(tmp).write_text(json.dumps(_jsonable(data), indent=2, default=str))


def _read_done(path: Path) -> dict | None:
    try:
        done = json.loads(path.read_text())
    except (FileNotFoundError, NotADirectoryError, json.JSONDecodeError, UnicodeDecodeError):
        return None
    return done if isinstance(done, dict) else None


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _recover(root: Path, say) -> None:
    """Clean what a killed run left in a subject folder: temporary and half-replaced folders."""
    if not root.is_dir():
        return
    for p in sorted(root.iterdir()):
        if not (p.name.startswith(".") and p.is_dir()):
            continue
        if ".tmp-" in p.name:
            shutil.rmtree(p, ignore_errors=True)
            say(f"[{root.name}] removed the unfinished stage folder {p.name} of an interrupted run")
        elif ".old-" in p.name:
            stage = p.name[1:].split(".old-")[0]
            if not (root / stage).exists():  # killed between the two renames: put it back
                os.rename(p, root / stage)
                say(f"[{root.name}] restored {stage}/ from an interrupted replacement")
            else:
                shutil.rmtree(p, ignore_errors=True)


def _commit(tmp: Path, final: Path) -> None:
    """Replace `final` by the complete folder `tmp` (two renames; never a mix of the two)."""
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.old-{secrets.token_hex(4)}"
        os.rename(final, old)
    os.rename(tmp, final)
    _fsync_dir(final.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


class _StageLog(logging.Handler):
    """Collects the library's log records (repairs, relabelled voxels ...) while a stage runs."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record):
        if record.name != log.name:  # the pipeline's own progress lines stay out
            self.lines.append(f"{record.levelname} {record.name}: {record.getMessage()}")


@contextlib.contextmanager
def _capture_log(folder: Path):
    """Write what the library logs at INFO and above during the block to `folder`/log.txt.

    STYLE.md: a repair is logged at INFO and shown in the run's report; the report page shows
    each stage's log.txt.
    """
    handler = _StageLog()
    lib = logging.getLogger("jaxhead")
    old_level = lib.level
    if lib.getEffectiveLevel() > logging.INFO:
        lib.setLevel(logging.INFO)
    lib.addHandler(handler)
    try:
        yield
    finally:
        lib.removeHandler(handler)
        lib.setLevel(old_level)
    if handler.lines:
        (folder / "log.txt").write_text("\n".join(handler.lines) + "\n")


def _oserror_text(e: OSError) -> str:
    if e.filename:
        return f"{e.strerror or type(e).__name__}: {str(e.filename)!r}"
    return str(e) or type(e).__name__


def subjects(cfg: RunConfig) -> list[Subject]:
    """The subjects a run processes (one per phantom modality, or the one input file)."""
    root = cfg.run_dir
    if cfg.input.source == "phantom":
        return [Subject(m, m, root / m) for m in cfg.input.modalities]
    return [Subject("subject", cfg.input.modality, root / "subject")]


def _stage_order(cfg: RunConfig, stages: dict) -> list[str]:
    names = list(stages) if cfg.stages is None else list(cfg.stages)
    if not names:
        raise ValueError(f"`stages` is empty, so the run would do nothing; list the stages to run, "
                         f"in order, from {list(stages)}, or leave `stages` out to run them all.")
    unknown = [n for n in names if n not in stages]
    if unknown:
        raise ValueError(
            f"unknown stage(s) {unknown} in `stages`; available, in order: {list(stages)}.")
    order = [n for n in stages if n in names]
    if order != names:
        raise ValueError(f"`stages` must follow pipeline order {list(stages)}; got {names}.")
    return order


def _make_run_dir(run_dir: Path) -> None:
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        probe = run_dir / f".write-test-{secrets.token_hex(4)}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise ValueError(
            f"cannot write the run folder {str(run_dir)!r} ({_oserror_text(e)}); set `out_dir` "
            "(or `jaxhead run --out`) to a folder you can write, or fix its permissions.") from None


def run_pipeline(cfg: RunConfig, *, force: bool = False, stages: dict[str, StageFn] | None = None,
                 progress: Callable[[str], None] | None = None, wait: bool = False,
                 heartbeat_s: float = 30.0, report: bool = True) -> dict:
    """Run every configured stage for every subject; returns {subject: {stage: summary}}.

    Arguments:
        cfg: the run configuration.
        force: rerun the configured stages even when they are up to date.
        stages: the stage functions by name, in pipeline order (default: `jaxhead.run.STAGES`);
            each may declare what it reads with `jaxhead.run.declare.stage`.
        progress: called with one line of text as stages start and finish (default: logging).
        wait: if another process is running in the same folder, wait for it instead of raising
            `RunLockedError`.
        heartbeat_s: seconds between "still running" lines when not on a terminal (0: none).
        report: write ``<run_dir>/report.html`` at the end (also after a failure).

    Raises:
        ValueError (StageError, RunLockedError): a bad config, a stage that failed on its input
            or environment, or a folder in use.
    """
    stages = STAGES if stages is None else stages
    order = _stage_order(cfg, stages)
    say = progress or log.info
    run_dir = cfg.run_dir
    _make_run_dir(run_dir)
    sections = [f.name for f in dataclasses.fields(cfg) if f.name not in ("name", "out_dir", "stages")]
    results: dict[str, dict] = {}
    with run_lock(run_dir, wait=wait, say=say):
        try:
            for subject in subjects(cfg):
                _recover(subject.root, say)
                results[subject.name] = {}
                for name in order:
                    earlier = list(stages)[:list(stages).index(name)]
                    spec = spec_of(stages[name], name, earlier, sections)
                    results[subject.name][name] = _run_stage(
                        cfg, subject, name, stages[name], spec, force, say, heartbeat_s)
        finally:
            if results:
                _write_json(run_dir / "summary.json", results)
            if report:
                try:
                    path = write_report(cfg, stages=list(stages))
                    say(f"report: {path}")
                except Exception as e:  # the report never hides the run's own outcome
                    log.warning("could not write the report page: %s: %s", type(e).__name__, e)
    return results


def _run_stage(cfg, subject: Subject, name: str, fn: StageFn, spec: StageSpec, force: bool,
               say, heartbeat_s: float) -> dict:
    label = f"[{subject.name}] {name}"
    final = subject.root / name
    fp = fingerprint(cfg, subject, name, spec)
    done = _read_done(final / DONE)
    reason = "--force" if force else why_stale(done, fp, final)
    if reason is None:
        say(f"{label}: up to date ({done.get('seconds', 0):.1f} s before), skipped")
        return done.get("summary", {})
    say(f"{label}: running ({reason}) ...")
    subject.root.mkdir(parents=True, exist_ok=True)
    tmp = subject.root / f".{name}.tmp-{secrets.token_hex(4)}"
    tmp.mkdir()
    staged = subject.staged(name, tmp, spec.reads_for(cfg))
    t0 = time.perf_counter()
    try:
        with heartbeat(label, say, every_s=heartbeat_s), _capture_log(tmp):
            try:
                summary = fn(cfg, staged) or {}
            except ValueError as e:
                raise StageError(f"{label}: {e}") from e
            except OSError as e:
                raise StageError(f"{label}: {_oserror_text(e)}") from e
            except MemoryError as e:
                raise StageError(f"{label}: out of memory ({e or 'no details'}); use a coarser "
                                 "voxel size or mesh, or a machine with more memory.") from e
        seconds = time.perf_counter() - t0
        outputs = folder_digests(tmp)
        _write_json(tmp / DONE, {
            "stage": name, "hash": _hash(fp), "fingerprint": fp, "outputs": outputs,
            "seconds": seconds, "summary": summary, "reason": reason,
            "finished": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")})
        _commit(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    say(f"{label}: done in {seconds:.1f} s")
    return summary
