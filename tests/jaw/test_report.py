"""``report.html`` seen as a person sees it: loaded in headless Chromium (software WebGL), shot,
and the picture checked: both arches drawn in their colours, the legend there, another view
drawing something else, and no request leaving the page. Skipped when no Chromium is
installed (``.ci/run`` installs Debian's ``chromium``)."""
from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from mjist import report
from mjist.jaw import occlusion

BROWSER = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
pytestmark = pytest.mark.skipif(BROWSER is None, reason="no Chromium here (apt install chromium)")


def shoot(page, view: int, tmp_path, tag: str) -> tuple[np.ndarray, list[str]]:
    """The page at ``#view=N`` as an RGB array (1400x1000), and every URL the browser's network
    log saw it request."""
    from PIL import Image

    png, log = tmp_path / f"{tag}.png", tmp_path / f"{tag}.net.json"
    # the browser's own traffic (updates, accounts, hints) is switched off, so any request the
    # network log records is the page's
    quiet = ["--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
             "--disable-default-apps", "--disable-client-side-phishing-detection", "--disable-domain-reliability",
             "--disable-features=OptimizationHints,OptimizationGuideModelDownloading,Translate,MediaRouter,AccountConsistency",
             "--disable-spell-checking"]
    p = subprocess.run([BROWSER, *quiet, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                        "--use-angle=swiftshader", "--window-size=1400,1000", "--virtual-time-budget=20000",
                        "--hide-scrollbars", f"--log-net-log={log}", f"--screenshot={png}", f"{page.resolve().as_uri()}#view={view}"],
                       capture_output=True, text=True, timeout=180)
    assert png.exists(), p.stderr[-2000:]
    return np.asarray(Image.open(png).convert("RGB"), dtype=np.int16), page_requests(log)


def page_requests(netlog) -> list[str]:
    """URLs the page (a file:// document) asked the network for, from Chromium's net log: the
    request jobs whose isolation key is the page's file:// site (the browser's own update and
    account traffic has another key)."""
    j = json.loads(netlog.read_text())
    start = j["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"]
    out = set()
    for e in j["events"]:
        p = e.get("params", {})
        if e["type"] == start and str(p.get("network_isolation_key", "")).startswith("file://") \
                and not str(p.get("url", "")).startswith(("file:", "data:", "blob:")):
            out.add(p["url"])
    return sorted(out)


def _plot(img):
    """The 3D canvas: left of the side panel, below the header."""
    return img[90:730, 20:1050]


def _arch_pixels(img) -> tuple[int, int]:
    """Pixels of the plot in the maxilla's ivory and the mandible's blue (lit: any shade)."""
    p = _plot(img)
    r, g, b = p[..., 0], p[..., 1], p[..., 2]
    white = (r > 245) & (g > 245) & (b > 245)
    ivory = ~white & (r > 90) & (r - b > 18) & (g - b > 8)
    blue = ~white & (b - r > 25) & (b > 90)
    return int(ivory.sum()), int(blue.sum())


def test_the_request_check_sees_a_page_that_fetches(tmp_path):
    """The net-log check itself: a page that loads an image and fetches JSON from the network is caught."""
    probe = tmp_path / "probe.html"
    probe.write_text('<html><body><img src="http://example.invalid/probe.png">'
                     '<script>fetch("https://example.invalid/f.json").catch(() => 0)</script></body></html>')
    _, urls = shoot(probe, 0, tmp_path, "probe")
    assert urls == ["http://example.invalid/probe.png", "https://example.invalid/f.json"]


def check_page(page, tmp_path, views=(0, 1)):
    """Both arches drawn, the legend's swatches on screen when there is a map, view ``views[1]``
    different from ``views[0]``, nothing fetched."""
    a, urls_a = shoot(page, views[0], tmp_path, "a")
    b, urls_b = shoot(page, views[1], tmp_path, "b")
    assert not urls_a and not urls_b, f"the page requested {urls_a + urls_b}"
    ivory, blue = _arch_pixels(a)
    assert ivory > 5000 and blue > 5000, (ivory, blue)
    changed = np.abs(_plot(a) - _plot(b)).sum(axis=2) > 60
    assert changed.mean() > 0.01, changed.mean()  # the other view draws the arches elsewhere
    return a, b


def _legend_on_screen(img) -> bool:
    """The contact map legend's red swatch (< 0.05 mm) in the side panel."""
    side = img[200:500, 1060:1100]
    return bool(((np.abs(side - [191, 13, 26]) < 12).all(axis=2)).sum() > 50)


@pytest.fixture(scope="module")
def bundled_occlusion(tmp_path_factory, cache):
    import os

    out = tmp_path_factory.mktemp("occ")
    os.environ.setdefault("MUJOCO_GL", "egl")
    assert occlusion.main(starts=24, seed=2, threads=2, out=str(out), progress=False, picture=False) == 0
    return out


def test_the_occlusion_report_draws_the_arches_map_and_switches_views(bundled_occlusion, tmp_path):
    page = bundled_occlusion / "report.html"
    assert page.exists() and page.stat().st_size < 15e6
    assert "default-src 'none'" in page.read_text()  # its policy forbids any fetch; the browser's log checks it
    occ = json.loads((bundled_occlusion / "occlusion.json").read_text())
    n = len(occ["candidates"])
    # two candidates: #1 and #2; one: #1 and the opened view
    a, b = check_page(page, tmp_path, (0, 1))
    assert _legend_on_screen(a)
    if n < 2:
        ivory, blue = _arch_pixels(b)  # opened: both occlusal surfaces face the viewer
        assert ivory > 5000 and blue > 5000


def test_the_report_rebuilds_from_the_output_folder_alone(bundled_occlusion, tmp_path):
    """``mjist view OUT --rebuild`` on a copy of the folder: the same page from the files."""
    from mjist import cli

    copy = tmp_path / "copy"
    shutil.copytree(bundled_occlusion, copy)
    (copy / "report.html").unlink()
    assert cli.main(["view", str(copy), "--rebuild"]) == 0

    def data(p):  # the arches, views and tables the page draws (its title names the folder)
        t = p.read_text()
        return t[t.index('id="mjist-data">'):t.index("</script>", t.index('id="mjist-data">'))], t.split("</header>")[1]

    assert data(copy / "report.html") == data(bundled_occlusion / "report.html")


def test_a_folder_without_results_is_refused_with_what_to_give(tmp_path, capsys):
    from mjist import cli

    assert cli.main(["view", str(tmp_path), "--rebuild"]) != 0
    err = capsys.readouterr().err
    assert "holds no occlusion.json, wafer.json or closure_ist.json" in err and "mjist occlusion" in err


def test_the_cohort_page_links_each_patient_failures_first(tmp_path):
    """A cohort folder's ``cohort.csv`` (one failed patient, one with a report): the page lists the
    failed one first, links the report, and draws in a browser without a request."""
    import csv

    (tmp_path / "patients" / "p1").mkdir(parents=True)
    (tmp_path / "patients" / "p1" / "report.html").write_text("<html></html>")
    with open(tmp_path / "cohort.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, ["patient", "status", "error", "design_max_mm"])
        w.writeheader()
        w.writerow({"patient": "p1", "status": "ok", "design_max_mm": "0.08"})
        w.writerow({"patient": "p2", "status": "error", "error": "maxilla: not a mesh"})
    page = report.write_cohort(tmp_path)
    text = page.read_text()
    assert text.index(">p2<") < text.index(">p1<") and "href='patients/p1/report.html'" in text
    img, urls = shoot(page, 0, tmp_path, "cohort")
    assert not urls
    assert ((np.abs(img - [251, 233, 233]) < 4).all(axis=2)).sum() > 500  # the failed row's tint on screen


@pytest.mark.slow  # a wafer made and proved (without the hold test)
def test_the_wafer_report_draws_the_wafer_between_the_arches(tmp_path, cache):
    from mjist.jaw import wafer

    out = tmp_path / "wafer" / "wafer.stl"
    res = wafer.make(None, output=out, picture=False, progress=False, cache_dir=cache, hold=False)
    page = report.build(out.parent)
    a, b = check_page(page, tmp_path, (0, 1))  # seated, then the wafer alone
    p = _plot(b)
    green = (p[..., 1] - p[..., 0] > 30) & (p[..., 1] - p[..., 2] > 20)
    assert green.sum() > 5000  # the wafer, drawn alone
    assert ("every proof holds" if res["ok"] else "a proof FAILS") in page.read_text()


@pytest.mark.slow  # trees of a user's pair, built once
def test_demo_with_data_writes_a_closure_report(tmp_path, cache, monkeypatch):
    from mjist.jaw import BUNDLED, demo

    monkeypatch.setenv("MJIST_CACHE", cache)
    folder = tmp_path / "pair"
    folder.mkdir()
    for f in ("maxilla.obj", "mandible.obj", "occlusion.json"):
        shutil.copy(BUNDLED / f, folder / f)
    out = tmp_path / "demo"
    assert demo.main(data=folder, seconds=0.3, out=out, picture=False, progress=False) == 0
    page = out / "report.html"
    check_page(page, tmp_path, (0, 2))  # closed, then opened


@pytest.mark.slow  # a whole default search on a real pair
@pytest.mark.shared
@pytest.mark.parametrize("pair", ["orthocast", "jaw"])
def test_real_pairs_get_a_report_that_draws(pair, tmp_path, cache, monkeypatch):
    """The shared casts and CBCT pair searched with default settings: their reports draw both
    arches and the map, the views differ, nothing is fetched."""
    from conftest import shared_path

    monkeypatch.setenv("MJIST_CACHE", cache)
    out = tmp_path / pair
    assert occlusion.main(data=shared_path(pair), out=str(out), progress=False, picture=False) == 0
    n = len(json.loads((out / "occlusion.json").read_text())["candidates"])
    a, _ = check_page(out / "report.html", tmp_path, (0, n))  # the best, then the arches opened
    assert _legend_on_screen(a)
    if n > 1:  # the runner-up: the mandible moved by its offset (CBCT: 0.8 mm, 0.3 % of the plot's pixels)
        b, _ = shoot(out / "report.html", 1, tmp_path, "runner_up")
        assert (np.abs(_plot(a) - _plot(b)).sum(axis=2) > 60).mean() > 5e-4
