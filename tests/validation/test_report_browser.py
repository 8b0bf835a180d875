"""The HTML report opens and looks right in a real browser (headless Chromium).

A screenshot of report.html must not be blank and must show the pictures:
the flow figures use the Middlebury colour coding, so loaded images put
strongly saturated pixels on screen, which text, tables and broken-image
placeholders never do. A control run of the same page with its figures
removed proves that this check notices images that did not load.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest

from validation.oracle import OracleConfig, TruthOracle
from validation.report import write_report
from validation.runner import run_validation
from validation.synthdata import demo_scene, write_synthetic_dataset

CHROMIUM = shutil.which("chromium") or (
    "/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None
)
pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="chromium is not installed (CI installs it in .ci/setup: apt-get install chromium)",
)


class _Images(HTMLParser):
    def __init__(self):
        super().__init__()
        self.src: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.src.append(dict(attrs).get("src", ""))


def _screenshot(page: Path, out: Path, profile: Path) -> np.ndarray:
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        f"--screenshot={out}",
        "--window-size=1280,4000",
        page.resolve().as_uri(),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.is_file(), f"no screenshot (chromium exit {proc.returncode}): {proc.stderr[-2000:]}"
    img = cv2.imread(str(out), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[:2] == (4000, 1280), None if img is None else img.shape
    return img


def _saturated_fraction(img: np.ndarray) -> float:
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    return float(np.mean((hsv[..., 1] > 100) & (hsv[..., 2] > 60)))


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("browser")
    ds = write_synthetic_dataset(
        root / "ds", demo_scene(64), 2, name="synthetic-demo", supersample=1
    )
    res = run_validation(
        ds, variants=[("truth-oracle", OracleConfig())], estimate=TruthOracle(ds), progress=False
    )
    write_report(res, root / "report", command="pytest")
    return root / "report"


def test_every_image_is_a_relative_existing_png(report):
    parser = _Images()
    parser.feed((report / "report.html").read_text())
    assert len(parser.src) >= 8
    for src in parser.src:
        assert not re.match(r"^[a-z]+:", src) and not src.startswith("/"), src
        path = report / src
        assert path.is_file(), src
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[0] > 50 and img.shape[1] > 50, src


@pytest.mark.slow  # 11.4 s (docs/decisions/slow_tests.md)
def test_report_renders_in_chromium(report, tmp_path):
    shot = _screenshot(report / "report.html", tmp_path / "shot.png", tmp_path / "profile")
    grey = cv2.cvtColor(shot, cv2.COLOR_BGR2GRAY)
    # Not blank: plenty of dark (text, frames) and light pixels, and many distinct colours.
    assert grey.std() > 30, grey.std()
    assert np.mean(grey < 80) > 0.01 and np.mean(grey > 200) > 0.2
    colours = np.unique(shot.reshape(-1, 3) // 8, axis=0).shape[0]
    assert colours > 500, colours
    # The flow pictures (Middlebury colours) are on screen: images loaded.
    loaded = _saturated_fraction(shot)
    assert loaded > 0.01, loaded

    # Control: the same page without its figures shows no such pixels.
    broken = tmp_path / "broken"
    broken.mkdir()
    shutil.copy(report / "report.html", broken / "report.html")
    shot2 = _screenshot(broken / "report.html", tmp_path / "shot2.png", tmp_path / "profile2")
    assert _saturated_fraction(shot2) < 0.2 * loaded
