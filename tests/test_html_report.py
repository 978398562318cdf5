"""`dualsight report --html`: the page loads in real headless Chromium (Debian's package; scripts/test.sh
installs it when missing) without JavaScript errors, and every figure is there with a non-zero size."""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from dualsight.jobs.cli.main import main

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (scripts/test.sh installs it)")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def load(page: Path, tmp: Path) -> dict:
    """The page's own load check (errors, figures with their sizes), read from the DOM Chromium rendered."""
    out = subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={tmp / 'profile'}", "--virtual-time-budget=5000",
                          "--window-size=1280,2000", "--dump-dom", page.resolve().as_uri()], capture_output=True,
                         text=True, timeout=120)
    m = re.search(r'data-check="([^"]*)"', out.stdout)
    assert m, f"the page did not finish loading: {out.stderr[-500:]}"
    return json.loads(html.unescape(m.group(1)))


def screenshot(page: Path, tmp: Path, png: Path):
    subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={tmp / 'profile2'}", "--window-size=1280,2400",
                    f"--screenshot={png}", page.resolve().as_uri()], capture_output=True, timeout=120)
    return png


ESA = Path("/work/shared/data/real/esa_tetra3")


@pytest.fixture(scope="module")
def lake(make_lake):
    hil = ([["hil", "star", *sorted(str(p) for p in ESA.glob("*.tiff"))[:2], "--camera",
             "examples/cameras/esa_tetra3.toml", "--truth", str(ESA / "truth.json"), "--run", "h"]]
           if ESA.is_dir() else [])
    return make_lake("lake",
                     *hil,
                     ["star", "run", "--cases", "40", "--run", "s"],
                     ["prox", "sweep", "--preset", "paper", "--orientations", "2", "--run", "p"],
                     ["prox", "trajectory", "--preset", "paper", "--frames", "12", "--run", "t"])


@pytest.mark.parametrize("run, figures", [
    ("s", {"fig9-10", "case-0"}),
    ("p", {"fig7", "fig1", "case-0"}),
    ("t", {"fig6", "fig1", "case-0"}),
    ("h", {"case-0"}),
])
def test_report_page_loads_with_every_figure(lake, tmp_path, run, figures):
    if run == "h" and not ESA.is_dir():
        pytest.skip(f"{ESA} absent")
    page = tmp_path / f"{run}.html"
    assert main(["report", "--lake", str(lake), "--run", run, "--html", str(page)]) == 0
    text = page.read_text()
    assert "http://" not in text and "https://" not in text          # self-contained: nothing fetched
    check = load(page, tmp_path)
    assert check["errors"] == []
    got = {f["id"]: f for f in check["figures"]}
    assert figures <= set(got), (figures, set(got))
    assert all(f["w"] > 0 and f["h"] > 0 and f["shown"] > 0 for f in check["figures"])
    assert all(f["varied"] > 50 for f in check["figures"]), check["figures"]      # decoded, not blank
    # fits a 1280 px window: no horizontal scrollbar on the page, no element scrolled sideways inside it
    assert check["viewport"] == 1280 and check["scrollWidth"] <= check["viewport"], check
    assert check["wide"] == [], check["wide"]
    png = screenshot(page, tmp_path, tmp_path / f"{run}.png")
    assert png.stat().st_size > 20_000


def test_report_refuses_a_missing_folder(lake, tmp_path, capsys):
    assert main(["report", "--lake", str(lake), "--run", "s", "--html", str(tmp_path / "no" / "x.html")]) == 2
    assert "folder does not exist" in capsys.readouterr().err and not (tmp_path / "no").exists()
