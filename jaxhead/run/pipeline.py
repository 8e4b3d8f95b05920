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
import enum
import glob
import hashlib
import json
import logging
import os
import secrets
import shutil
import sys
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

import jax
from distributed import as_completed
from tqdm import tqdm

from .._files import atomic_write_path, file_digest, write_csv
from ..io import VOLUME_EXTENSIONS
from ..study import connect
from .config import RunConfig, is_pattern
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
        # Tissue keys by name; other keys as they are (file names and paths keep their case:
        # done.json's output and input-file names are compared with the folder's).
        return {k.name.lower() if isinstance(k, enum.Enum) else str(k): _jsonable(v)
                for k, v in obj.items()}
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
    fp = {"version": package_version(), "config": config, "inputs": inputs, "files": _named_files(config, {})}
    if spec.versions:  # only where declared: other stages' fingerprints (and done.json) stay as they were
        fp["data_versions"] = dict(spec.versions)
    return fp


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
               + _changes(old.get("files"), fp["files"], "file")
               + _changes(old.get("data_versions"), fp.get("data_versions"), "data version"))
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


_BIDS_ENTITIES = ("sub", "ses")


def subject_name(path: str | os.PathLike) -> str:
    """A cohort subject's folder name: its BIDS `sub-XX` (and `ses-YY`) entities, else its stem.

    The entities are read from the file name first, then from its folders
    (``data/sub-01/ses-2/anat/T1w.nii.gz`` -> ``sub-01_ses-2``); a path without ``sub-`` gives
    the file name without its extension (``.nii.gz``, ``.nii``, ``.hdr``, ``.img``).
    """
    path = Path(path)
    found = {}
    for part in [path.name, *reversed(path.parent.parts)]:
        for token in part.split("_"):
            key, sep, value = token.partition("-")
            if sep and key in _BIDS_ENTITIES and key not in found and value \
                    and value.split(".")[0].isalnum():
                found[key] = f"{key}-{value.split('.')[0]}"
    if "sub" in found:
        return "_".join(found[k] for k in _BIDS_ENTITIES if k in found)
    name = path.name
    for ext in sorted(VOLUME_EXTENSIONS, key=len, reverse=True):
        if name.lower().endswith(ext):
            return name[:-len(ext)]
    return path.stem


def cohort_files(cfg: RunConfig) -> list[str]:
    """The scans of a cohort config (`[input] path` a pattern or a list), in sorted order.

    Raises:
        ValueError: a pattern that matches no file, or a listed file that does not exist.
    """
    entries = (cfg.input.path,) if isinstance(cfg.input.path, str) else cfg.input.path
    files = []
    for entry in entries:
        if Path(entry).is_file():
            files.append(entry)
        elif is_pattern(entry):
            matched = sorted(p for p in glob.glob(entry, recursive=True) if Path(p).is_file())
            if not matched:
                raise ValueError(
                    f"[input] `path` pattern {entry!r} matches no file (relative to "
                    f"{Path.cwd()}); check the pattern, e.g. \"data/sub-*/anat/*_T1w.nii.gz\", "
                    "or list the scans.")
            files += matched
        else:
            raise ValueError(f"[input] `path` entry {entry!r} is not a file (relative paths are "
                             f"relative to {Path.cwd()}); fix or remove it.")
    return files


def subjects(cfg: RunConfig) -> list[Subject]:
    """The subjects a run processes: one per phantom modality, the one input file (folder
    "subject"), or one per file of a cohort (`[input] path` a pattern or list; `subject_name`).

    Raises:
        ValueError: a cohort pattern matching nothing, a missing file, or two files with one
            subject name (both named).
    """
    root = cfg.run_dir
    if cfg.input.source == "phantom":
        return [Subject(m, m, root / m) for m in cfg.input.modalities]
    if not cfg.input.is_cohort:
        return [Subject("subject", cfg.input.modality, root / "subject")]
    out: dict[str, Subject] = {}
    for f in cohort_files(cfg):
        name = subject_name(f)
        if name in out:
            raise ValueError(
                f"[input] `path` = {cfg.input.path!r}: {out[name].path!r} and {f!r} are both "
                f"subject {name!r} (one folder each); narrow the pattern to one scan per "
                "subject and session (e.g. *_run-1_T1w.nii.gz), or list the files.")
        out[name] = Subject(name, cfg.input.modality, root / name, path=f)
    return list(out.values())


def subject_config(cfg: RunConfig, subject: Subject) -> RunConfig:
    """The config one subject's stages run with: a cohort's `[input] path` is its own file."""
    if subject.path is None:
        return cfg
    return dataclasses.replace(cfg, input=dataclasses.replace(cfg.input, path=subject.path))


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
                 heartbeat_s: float = 30.0, report: bool = True, workers: int | None = None,
                 scheduler: str | None = None) -> dict:
    """Run every configured stage for every subject; returns {subject: {stage: summary}}.

    Subjects are independent: a subject that fails is recorded (its error in
    ``<run_dir>/subjects.csv`` and summary.json) and the others still run; the error is raised
    at the end. With `workers` >= 2 or a `scheduler`, each subject is a Dask task
    (`jaxhead.study.connect`: an embedded LocalCluster of single-threaded processes, or a
    running scheduler); otherwise they run one after the other in this process.

    Arguments:
        cfg: the run configuration.
        force: rerun the configured stages even when they are up to date.
        stages: the stage functions by name, in pipeline order (default: `jaxhead.run.STAGES`);
            each may declare what it reads with `jaxhead.run.declare.stage`.
        progress: called with one line of text as stages start and finish (default: logging).
            Subjects run by workers report their lines when they finish.
        wait: if another process is running in the same folder, wait for it instead of raising
            `RunLockedError`.
        heartbeat_s: seconds between "still running" lines when not on a terminal (0: none).
        report: write ``<run_dir>/report.html`` at the end (also after a failure).
        workers: processes of an embedded Dask cluster, one subject per task (None or 1: in
            this process).
        scheduler: address of a running Dask scheduler ("tcp://host:8786") instead.

    Raises:
        ValueError (StageError, RunLockedError): a bad config, a stage that failed on its input
            or environment (with several subjects failed: StageError naming each), or a folder
            in use. A subject's unexpected error (a bug) in a one-subject run is re-raised as is.
    """
    stages = STAGES if stages is None else stages
    order = _stage_order(cfg, stages)
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers
                                or workers < 1):
        raise ValueError(f"`workers` = {workers!r}; use a whole number >= 1 (1: in this "
                         "process).")
    say = progress or log.info
    run_dir = cfg.run_dir
    todo = subjects(cfg)  # a cohort pattern matching nothing: an error before any work
    _make_run_dir(run_dir)
    rows: dict[str, dict] = {}
    errors: dict[str, BaseException] = {}
    with run_lock(run_dir, wait=wait, say=say):
        try:
            if workers in (None, 1) and scheduler is None:
                for subject in todo:
                    row, exc = _subject(cfg, subject, order, stages, force, say, heartbeat_s)
                    rows[subject.name] = row
                    if exc is not None:
                        errors[subject.name] = exc
            else:
                _run_tasks(cfg, todo, order, stages, force, say, heartbeat_s, workers,
                           scheduler, rows)
        finally:
            if rows:
                results = {n: r["stages"] | ({"error": r["error"]} if r["error"] else {})
                           for n, r in rows.items()}
                _write_json(run_dir / "summary.json", results)
                write_csv(run_dir / SUBJECTS_CSV, SUBJECT_COLUMNS,
                          [r | {"seconds": f"{r['seconds']:.1f}"} for r in rows.values()])
            if report:
                try:
                    path = write_report(cfg, stages=list(stages))
                    say(f"report: {path}")
                except Exception as e:  # the report never hides the run's own outcome
                    log.warning("could not write the report page: %s: %s", type(e).__name__, e)
    failed = [r for r in rows.values() if r["status"] != "done"]
    if len(failed) == 1 and failed[0]["subject"] in errors:
        raise errors[failed[0]["subject"]]  # its own exception, as before cohorts
    if failed:
        text = "; ".join(f"[{r['subject']}] {r['error']}" for r in failed)
        err = StageError(f"{len(failed)} of {len(rows)} subjects failed ({text}); the others "
                         f"finished. See {run_dir / SUBJECTS_CSV}; a rerun retries them.")
        err.results = {n: r["stages"] for n, r in rows.items()}
        raise err
    return {n: r["stages"] for n, r in rows.items()}


SUBJECTS_CSV = "subjects.csv"
#: subjects.csv columns: the cohort table (n_tets when the run meshed the subject).
SUBJECT_COLUMNS = ("subject", "path", "status", "seconds", "n_tets", "error")


def _error_text(e: BaseException, subject: str) -> str:
    """One line for subjects.csv: the error without the subject's own "[name] " label."""
    text = " ".join(str(e).split())
    if not isinstance(e, StageError):
        return f"{type(e).__name__}: {text}"
    return text.removeprefix(f"[{subject}] ")


def _subject(cfg: RunConfig, subject: Subject, order: list[str], stages: dict, force: bool, say,
             heartbeat_s: float) -> tuple[dict, Exception | None]:
    """Run one subject's stages under its lock: (its subjects.csv row + stage summaries, the
    exception that stopped it or None)."""
    scfg = subject_config(cfg, subject)
    sections = [f.name for f in dataclasses.fields(cfg) if f.name not in ("name", "out_dir", "stages")]
    row = {"subject": subject.name, "path": subject.path or (scfg.input.path or ""),
           "status": "failed", "seconds": 0.0, "n_tets": "", "error": "", "stages": {}}
    t0 = time.perf_counter()
    exc = None
    try:
        with run_lock(cfg.run_dir, wait=True, say=say, subject=subject.name):
            _recover(subject.root, say)
            for name in order:
                earlier = list(stages)[:list(stages).index(name)]
                spec = spec_of(stages[name], name, earlier, sections)
                row["stages"][name] = _run_stage(scfg, subject, name, stages[name], spec, force,
                                                 say, heartbeat_s)
        row["status"] = "done"
    except Exception as e:  # noqa: BLE001 (recorded; the other subjects still run)
        exc = e
        row["error"] = _error_text(e, subject.name)
    row["seconds"] = time.perf_counter() - t0
    mesh = row["stages"].get("mesh") or {}
    row["n_tets"] = mesh.get("n_tets", "") if isinstance(mesh, dict) else ""
    return row, exc


def run_subject(cfg: RunConfig, subject: Subject, order: list[str], stages: dict, force: bool,
                heartbeat_s: float, x64: bool) -> dict:
    """One subject as a Dask task (plain, picklable arguments): its row, with the progress
    lines it would have printed under "lines". A failure is in the row, never raised."""
    jax.config.update("jax_enable_x64", x64)  # the driver's setting (the CLI's: float64)
    lines: list[str] = []
    row, _ = _subject(cfg, subject, order, stages, force, lines.append, heartbeat_s)
    return row | {"lines": lines}


def _run_tasks(cfg, todo, order, stages, force, say, heartbeat_s, workers, scheduler,
               rows: dict) -> None:
    """Run the subjects as Dask tasks, filling `rows` as they finish."""
    client, cluster = connect(workers, scheduler)  # an unreachable scheduler fails here
    try:
        x64 = bool(jax.config.read("jax_enable_x64"))
        futures = {client.submit(run_subject, cfg, s, order, stages, force, heartbeat_s, x64,
                                 pure=False, key=f"jaxhead-subject-{s.name}-{secrets.token_hex(4)}"): s
                   for s in todo}
        say(f"{len(todo)} subjects as Dask tasks on {client.scheduler.address}")
        bar = tqdm(total=len(todo), desc="subjects", unit="subject") if sys.stderr.isatty() else None
        for fut in as_completed(futures):
            s = futures[fut]
            try:
                row = fut.result()
            except Exception as e:  # noqa: BLE001 (a worker died: recorded, the others run)
                row = {"subject": s.name, "path": s.path or "", "status": "failed",
                       "seconds": 0.0, "n_tets": "", "error": _error_text(e, s.name), "stages": {}}
            for line in row.pop("lines", []):
                say(line)
            rows[s.name] = row
            say(f"[{s.name}] {row['status']} in {row['seconds']:.1f} s"
                + (f": {row['error']}" if row["error"] else ""))
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    for s in todo:  # subjects.csv in the cohort's order, not the order they finished
        rows[s.name] = rows.pop(s.name)


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
