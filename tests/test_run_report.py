"""report.html: one self-contained page per run, rendered in headless Chromium with every image.

The Chromium test needs Debian's `chromium` package (`apt-get install chromium`) and is skipped,
saying so, without it.
"""

import re
import shutil
import subprocess

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

from jaxhead.run import stage  # noqa: E402
from jaxhead.run.config import InputConfig, RunConfig  # noqa: E402
from jaxhead.run.pipeline import run_pipeline  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _png(path, title):
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1, 2], [0, 1, 0])
    ax.set_title(title)
    fig.savefig(path, dpi=60)
    plt.close(fig)


def _fake_run(tmp_path):
    @stage(config=("input",))
    def run_input(cfg, subject):
        _png(subject.dir("input") / "overlay.png", f"{subject.name} overlay")
        return {"shape": [10, 10, 10]}

    @stage(config=(), reads=("input",))
    def run_quality(cfg, subject):
        out = subject.dir("quality")
        _png(out / "hist_brain.png", "brain histogram")
        (out / "table2.txt").write_text("tissue  tets  min_quality\nbrain   1000  0.12 <&>\n")
        return {"table2": [1, 2, 3]}

    cfg = RunConfig(name="report-test", out_dir=str(tmp_path / "run"),
                    input=InputConfig(modalities=("mri", "ct")))
    run_pipeline(cfg, stages={"input": run_input, "quality": run_quality},
                 progress=lambda s: None)
    return cfg


def test_report_page_is_self_contained(tmp_path):
    cfg = _fake_run(tmp_path)
    page = (tmp_path / "run/report.html").read_text()
    assert page.count("data:image/png;base64,") == 4  # 2 subjects x 2 figures, inlined
    assert not re.search(r'src="(?!data:)', page)  # nothing to fetch: opens offline
    assert "brain   1000  0.12 &lt;&amp;&gt;" in page  # tables escaped, verbatim
    for text in ("provenance", "version jaxhead", "pytetwild", "sha256", "report-test",
                 "&quot;seed&quot;: 0", "table2"):
        assert text in page, text
    assert cfg.run_dir.joinpath("report.html").stat().st_size > 10_000


@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium package for headless "
                                             "rendering: apt-get install chromium")
def test_report_renders_in_chromium_with_every_image(tmp_path):
    _fake_run(tmp_path)
    url = (tmp_path / "run/report.html").resolve().as_uri()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=5000"]
    dom = subprocess.run([CHROMIUM, *flags, "--dump-dom", url], capture_output=True, text=True,
                         timeout=120).stdout
    # The page's own onload script counts images that decoded (naturalWidth > 0).
    assert 'data-images="4/4"' in dom, dom[:300]
    shot = tmp_path / "report.png"
    subprocess.run([CHROMIUM, *flags, f"--screenshot={shot}", "--window-size=1200,2000", url],
                   capture_output=True, timeout=120)
    assert shot.exists() and shot.stat().st_size > 20_000
    # The check can fail: a page with a broken image reports it.
    broken = tmp_path / "run/broken.html"
    broken.write_text((tmp_path / "run/report.html").read_text().replace(
        "data:image/png;base64,iVBOR", "data:image/png;base64,AAAA", 1))
    dom = subprocess.run([CHROMIUM, *flags, "--dump-dom", broken.as_uri()], capture_output=True,
                         text=True, timeout=120).stdout
    assert 'data-images="3/4"' in dom
