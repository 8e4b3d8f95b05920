"""``<run_dir>/report.html``: one self-contained page of a run (images inlined, opens offline).

Per subject and stage it shows the figures and tables the stages already wrote (overlay,
segmentation and Dice, layers report, surface repair, mesh cut, Table 2 and histograms,
electrodes, scalp potential, reconstruction, fit table), the stage's summary and time, and the
provenance: jaxhead version, the config, the input files' digests, the mesher and the seeds.
Nothing is computed here; the page only gathers files.  [host]
"""

import base64
import datetime
import html
import json
import platform
import sys
from importlib import metadata
from pathlib import Path

from .._files import atomic_write_path
from .config import RunConfig

#: Text files shown verbatim, and how many lines of each at most.
_TEXT = {".txt": 200, ".csv": 40}
#: Files left off the page (large or shown otherwise).
_SKIP = {"done.json", "voltages.csv", "protocol.csv"}

_CSS = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1200px;color:#222}
h1{margin-bottom:0} h2{border-bottom:2px solid #ccc;margin-top:2em}
h3{margin-bottom:.3em} .meta{color:#666} .fail{color:#b00}
img{max-width:100%;border:1px solid #ddd;margin:.3em 0}
.figs{display:grid;grid-template-columns:repeat(auto-fill,minmax(360px,1fr));gap:.5em}
pre{background:#f6f6f6;padding:.6em;overflow-x:auto;font-size:12px}
table{border-collapse:collapse;font-size:13px} td,th{border:1px solid #ddd;padding:2px 6px;text-align:left}
details{margin:.4em 0}
"""

#: Marks the body with how many images decoded (checked by the Chromium test; harmless offline).
_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++;
  document.body.setAttribute('data-images', ok + '/' + imgs.length);
});
"""


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def _img(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return (f'<figure><img alt="{html.escape(path.name)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(path.name)}</figcaption></figure>")


def _text(path: Path, max_lines: int) -> str:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as e:
        return f"<p class=fail>{html.escape(str(e))}</p>"
    more = f"\n... ({len(lines) - max_lines} more lines in {path.name})" if len(lines) > max_lines else ""
    return (f"<h4>{html.escape(path.name)}</h4><pre>{html.escape(chr(10).join(lines[:max_lines]))}"
            f"{html.escape(more)}</pre>")


def _table(d: dict) -> str:
    rows = "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(json.dumps(v, default=str))}</td></tr>"
        for k, v in d.items())
    return f"<table>{rows}</table>"


def _stage_html(name: str, folder: Path) -> str:
    try:
        done = json.loads((folder / "done.json").read_text())
    except (OSError, ValueError):
        done = None
    if done is None:
        return (f"<h3>{name}</h3><p class=fail>not complete (no done.json): the stage has not "
                "run, or failed; see the run's log.</p>")
    parts = [f"<h3>{name}</h3><p class=meta>{done.get('seconds', 0):.1f} s, finished "
             f"{html.escape(str(done.get('finished', '?')))}; ran because: "
             f"{html.escape(str(done.get('reason', '?')))}</p>"]
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.name not in _SKIP)
    figs = [_img(p) for p in files if p.suffix == ".png"]
    if figs:
        parts.append(f"<div class=figs>{''.join(figs)}</div>")
    parts += [_text(p, _TEXT[p.suffix]) for p in files if p.suffix in _TEXT]
    summary = done.get("summary") or {}
    if summary:
        parts.append(f"<details><summary>summary</summary>{_table(summary)}</details>")
    fp = done.get("fingerprint") or {}
    digests = {**(fp.get("inputs") or {}), **(fp.get("files") or {})}
    if digests:
        parts.append("<details><summary>inputs (sha256)</summary>"
                     f"{_table(digests)}</details>")
    outputs = done.get("outputs") or {}
    if outputs:
        parts.append(f"<details><summary>outputs (sha256)</summary>{_table(outputs)}</details>")
    return "".join(parts)


def _jsonable(obj):
    if hasattr(obj, "__dataclass_fields__"):
        return {k: _jsonable(getattr(obj, k)) for k in obj.__dataclass_fields__}
    if isinstance(obj, dict):
        return {str(getattr(k, "name", k)).lower(): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


def write_report(cfg: RunConfig, *, stages: list[str] | None = None) -> Path:
    """Write ``<run_dir>/report.html`` from what the run folder holds now; returns its path.

    Arguments:
        cfg: the run's config (the page shows it as provenance).
        stages: stage names in pipeline order (default: `jaxhead.run.STAGES`' order is not
            imported here; folders are shown in this order, then any others alphabetically).
    """
    run_dir = cfg.run_dir
    order = list(stages or ["input", "segment", "layers", "surfaces", "mesh", "export",
                            "quality", "forward", "inverse"])
    subjects = sorted(p for p in run_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    body = []
    toc = []
    for subj in subjects:
        folders = [subj / s for s in order if (subj / s).is_dir()]
        folders += sorted(p for p in subj.iterdir() if p.is_dir() and not p.name.startswith(".")
                          and p.name not in order)
        if not folders:
            continue
        total = 0.0
        for f in folders:
            try:
                total += float(json.loads((f / "done.json").read_text()).get("seconds", 0))
            except (OSError, ValueError):
                pass
        toc.append(f'<li><a href="#{html.escape(subj.name)}">{html.escape(subj.name)}</a></li>')
        body.append(f'<h2 id="{html.escape(subj.name)}">{html.escape(subj.name)} '
                    f"<span class=meta>({total:.0f} s over {len(folders)} stages)</span></h2>")
        body += [_stage_html(f.name, f) for f in folders]
    now = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    versions = {d: _version(d) for d in ("jaxhead", "jax", "numpy", "scipy", "nibabel",
                                         "pytetwild", "meshio", "trimesh")}
    prov = {
        "written": now, "run folder": str(run_dir.resolve()),
        "python": sys.version.split()[0], "platform": platform.platform(),
        **{f"version {k}": v for k, v in versions.items()},
        "mesher": f"fTetWild via pytetwild {versions['pytetwild']}",
        "atlas": (f"default atlas: {cfg.segment.atlas_subjects} jaxhead.phantom heads at "
                  f"{cfg.segment.atlas_voxel_mm} mm ([segment] atlas_subjects, atlas_voxel_mm)"),
        "seeds": {"input": cfg.input.seed, "inverse": cfg.inverse.seed},
    }
    config = json.dumps(_jsonable(cfg), indent=2, default=str)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>jaxhead run {html.escape(cfg.name)}</title><style>{_CSS}</style></head>
<body>
<h1>jaxhead run: {html.escape(cfg.name)}</h1>
<p class=meta>{html.escape(str(run_dir))}, written {now}</p>
<ul>{''.join(toc)}<li><a href="#provenance">provenance</a></li></ul>
{''.join(body) or '<p class=fail>no stage has finished yet.</p>'}
<h2 id="provenance">provenance</h2>
{_table(prov)}
<details><summary>config</summary><pre>{html.escape(config)}</pre></details>
<script>{_SCRIPT}</script>
</body></html>
"""
    path = run_dir / "report.html"
    with atomic_write_path(path) as tmp:
        Path(tmp).write_text(page, encoding="utf-8")
    return path
