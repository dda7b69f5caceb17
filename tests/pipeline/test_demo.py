"""A reduced demo run: the report exists, holds every section, and renders with its images in Chromium."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from polspike.commands.demo import REPORT_SECTIONS, run_demo


@pytest.fixture(scope="module")
def demo_report(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    return run_demo(out, quick=True)


def test_report_holds_every_section(demo_report):
    html = demo_report.read_text()
    for sid in REPORT_SECTIONS:
        assert f'<section id="{sid}">' in html, sid
    imgs = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', html)
    assert len(imgs) >= 3


def test_report_renders_in_headless_chromium(demo_report, tmp_path):
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("chromium not installed (make test installs it as root)")
    shot = tmp_path / "shot.png"
    cmd = [
        exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1200,2400", "--hide-scrollbars",
        f"--screenshot={shot}", demo_report.resolve().as_uri(),
    ]
    subprocess.run(cmd, capture_output=True, timeout=120)
    assert shot.is_file(), "chromium wrote no screenshot"
    from skimage.io import imread

    img = imread(shot)[..., :3].astype(np.float64)
    non_white = np.mean(np.any(img < 240, axis=-1))
    colourful = np.mean(np.ptp(img, axis=-1) > 40)
    assert non_white > 0.15  # figures, not an empty page
    assert colourful > 0.01  # colour maps of the embedded figures were drawn
