"""Command line: parse arguments, build the config, call the public functions. Nothing else."""

import argparse
import dataclasses
import logging
import os
import sys
import traceback
from pathlib import Path

from . import io
from .phantom import make_head
from .run import load_config, run_pipeline, write_report
from .study import load_study_config, run_study


def _setup_runtime() -> None:
    # Entry point: float64 for FEM (STYLE.md, convention 3); the library never flips this itself.
    os.environ.setdefault("MPLBACKEND", "Agg")
    import jax

    jax.config.update("jax_enable_x64", True)


def _out_dir(cfg, args):
    """The config with `--out` (when given) as its output folder."""
    return dataclasses.replace(cfg, out_dir=args.out) if args.out else cfg


def _cmd_run(args) -> int:
    cfg = _out_dir(load_config(args.config), args)
    results = run_pipeline(cfg, force=args.force, wait=args.wait, workers=args.workers,
                           scheduler=args.scheduler, progress=lambda s: print(s, flush=True))
    print(f"run folder: {cfg.run_dir.resolve()}")
    for subject, stages in results.items():
        print(f"  {subject}: {', '.join(stages)}")
    return 0


def _cmd_report(args) -> int:
    cfg = _out_dir(load_config(args.config), args)
    if not cfg.run_dir.is_dir():
        raise FileNotFoundError(f"run folder {str(cfg.run_dir)!r} does not exist; run "
                                f"`jaxhead run {args.config}` first.")
    print(f"wrote {write_report(cfg)}")
    return 0


def _cmd_study(args) -> int:
    cfg = _out_dir(load_study_config(args.config), args)
    path = run_study(cfg, workers=args.workers, scheduler=args.scheduler,
                     progress=False if args.no_progress else None)
    print(f"study folder: {path}")
    return 0


def _cmd_phantom(args) -> int:
    kw = {} if args.noise is None else {"noise": args.noise}
    volume, labels = make_head(args.modality, voxel_mm=args.voxel_mm, seed=args.seed, **kw)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scan = out / f"phantom_{args.modality}_seed{args.seed}.nii.gz"
    lab = out / f"phantom_{args.modality}_seed{args.seed}_labels.nii.gz"
    io.save_volume(volume, scan)
    io.save_labels(labels, lab)
    print(f"wrote {scan}\nwrote {lab}")
    return 0


def _cmd_info(args) -> int:
    print(io.format_info(io.info(args.path)))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="jaxhead",
        description="Subject-specific, differentiable finite-element head models for EIT.")
    p.add_argument("-v", "--verbose", action="store_true", help="log at DEBUG level")
    p.add_argument("--debug", action="store_true",
                   help="on an error, print the full traceback (default: one line)")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run the stages of a TOML config into its run folder")
    r.add_argument("config", help="TOML run config, e.g. configs/demo.toml")
    r.add_argument("--force", action="store_true", help="rerun stages that are up to date")
    r.add_argument("--out", help="run folder (overrides the config's out_dir)")
    r.add_argument("--wait", action="store_true",
                   help="if another jaxhead run uses the folder, wait for it (default: refuse)")
    r.add_argument("--workers", type=int, default=None,
                   help="run the subjects (a cohort's scans) as tasks on an embedded Dask cluster "
                        "of this many processes (default: one after the other, in this process)")
    r.add_argument("--scheduler", default=None,
                   help="address of a running Dask scheduler (e.g. tcp://host:8786) for the "
                        "subjects' tasks instead")
    r.set_defaults(fn=_cmd_run)

    rp = sub.add_parser("report", help="(re)write <run folder>/report.html from a run's files")
    rp.add_argument("config", help="the run's TOML config")
    rp.add_argument("--out", help="run folder (overrides the config's out_dir)")
    rp.set_defaults(fn=_cmd_report)

    st = sub.add_parser(
        "study", help="segmentation-error study: perturbed heads as Dask tasks",
        description="Run a [study] config: perturb the reference head N times (morph or re-mesh), "
                    "measure voltages, images and fitted conductivities, and write "
                    "<out_dir>/study/{samples.csv,summary.json,figures}. Reruns skip finished samples.")
    st.add_argument("config", help="TOML file with a [study] section, e.g. configs/study_quick.toml")
    st.add_argument("--workers", type=int, default=None,
                    help="processes of the embedded Dask cluster (default: cores)")
    st.add_argument("--scheduler", default=None,
                    help="address of a running Dask scheduler (e.g. tcp://host:8786) instead")
    st.add_argument("--out", help="study folder parent (overrides the config's out_dir)")
    st.add_argument("--no-progress", action="store_true", help="no progress bar")
    st.set_defaults(fn=_cmd_study)

    ph = sub.add_parser("phantom", help="write a synthetic head scan and its labels as NIfTI")
    ph.add_argument("--modality", choices=["mri", "ct"], default="mri")
    ph.add_argument("--voxel-mm", type=float, default=1.0)
    ph.add_argument("--seed", type=int, default=0)
    ph.add_argument("--noise", type=float, default=None)
    ph.add_argument("--out", default=".", help="output folder")
    ph.set_defaults(fn=_cmd_phantom)

    i = sub.add_parser("info", help="shape, voxel size, orientation, intensity range of a volume")
    i.add_argument("path")
    i.set_defaults(fn=_cmd_info)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    _setup_runtime()
    try:
        return args.fn(args)
    except KeyboardInterrupt:
        print("jaxhead: interrupted; finished stages are kept, a rerun resumes.", file=sys.stderr)
        return 130
    except (ValueError, OSError, MemoryError) as e:
        # Expected failures (bad input, config, files, folder in use): one line, exit 2.
        if args.debug:
            traceback.print_exc()
        text = str(e) if not isinstance(e, MemoryError) else f"out of memory: {e}"
        if isinstance(e, OSError) and e.filename and str(e.filename) not in text:
            text = f"{text} ({e.filename})"
        print(f"jaxhead: error: {' '.join(text.split())}", file=sys.stderr)
        return 2
    except Exception as e:  # a bug: still one line, the traceback on request
        if args.debug:
            traceback.print_exc()
        print(f"jaxhead: internal error: {type(e).__name__}: {' '.join(str(e).split())} "
              "(rerun with --debug for the traceback, and please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
