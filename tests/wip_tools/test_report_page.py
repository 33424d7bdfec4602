"""report.html: one self-contained page per run, rendered by headless Chromium.

A short in-process run of the paper scenario (no ROS) is written by the same
``write_run_outputs`` as ``scripts/simulate`` and ``scripts/report``. The page must embed
every figure (data URIs only: it opens alone), give each a caption that explains its known
effects, hold the claims table and every metrics key with its meaning; Chromium must load
and decode every figure (checked from the DOM after load) and draw the page (a screenshot
that is not blank). SVG files lie beside the PNGs. The README documents every metrics key.

Chromium: CI is a fresh Debian 12 machine, as root with apt: the fixture installs
``chromium`` with apt-get when it is missing (once; idempotent), and skips with the reason
only when that is impossible (not root, no apt-get, the install failed).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re
import shutil
import subprocess
import xml.etree.ElementTree as ElementTree

import numpy as np
import pytest

from wip_tools.analysis.figures import FIGURE_NAMES
from wip_tools.analysis.report_page import flatten_metrics, METRIC_DOCS
from wip_tools.analysis.metrics import compute_metrics
from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import Scenario
from wip_tools.simulate import write_run_outputs

REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]
CHROMIUM_PACKAGES = ('chromium', 'fonts-dejavu-core')
#: Past the 30 s pulse of the paper scenario, so that its captions have their numbers.
DURATION = 32.0


def find_chromium() -> str | None:
    for name in ('chromium', 'chromium-browser', 'google-chrome'):
        path = shutil.which(name)
        if path:
            return path
    return None


@pytest.fixture(scope='session')
def chromium() -> str:
    """Chromium's path; installed with apt-get if missing (root only)."""
    path = find_chromium()
    if path:
        return path
    if os.geteuid() != 0 or not shutil.which('apt-get'):
        pytest.skip('chromium is not installed and cannot be (not root, or no apt-get): '
                    'apt-get install chromium')
    env = dict(os.environ, DEBIAN_FRONTEND='noninteractive')
    for command in (['apt-get', 'update'],
                    ['apt-get', 'install', '-y', '--no-install-recommends',
                     *CHROMIUM_PACKAGES]):
        result = subprocess.run(command, env=env, capture_output=True, text=True,
                                timeout=900, check=False)
        if result.returncode != 0:
            pytest.skip(f'{" ".join(command)} failed (exit {result.returncode}): '
                        f'{result.stderr.strip().splitlines()[-1:]}')
    path = find_chromium()
    if not path:
        pytest.skip('apt-get installed chromium but no chromium executable is on PATH')
    return path


@pytest.fixture(scope='module')
def run_dir(tmp_path_factory):
    scenario = dataclasses.replace(Scenario(), duration=DURATION)
    result = run_scenario(scenario)
    metrics = compute_metrics(result.record, scenario, fell=result.fell,
                              duration_s=result.simulated_time_s)
    out = tmp_path_factory.mktemp('report_page')
    steps = []
    write_run_outputs(out, result.record, scenario, metrics, figures=True,
                      progress=steps.append)
    assert steps[-1] == 'report.html' and len(steps) == len(FIGURE_NAMES)
    return out


def test_page_is_self_contained_with_every_figure_captioned(run_dir):
    text = (run_dir / 'report.html').read_text(encoding='utf-8')
    sources = re.findall(r'<img[^>]*\ssrc="([^"]+)"', text)
    assert len(sources) == len(FIGURE_NAMES)
    assert all(s.startswith('data:image/png;base64,') for s in sources)
    # Nothing else is loaded from outside the file (the SVG links are plain links).
    assert not re.search(r'<(script|link|iframe)\b', text)
    for name in FIGURE_NAMES:
        caption = re.search(rf'<figure id="{name}">.*?<figcaption>(.*?)</figcaption>', text,
                            re.S)
        assert caption, name
        assert len(re.sub('<[^>]+>', '', caption.group(1))) > 80, name
    # The known effects are explained where they show.
    assert re.search(r'fig07_velocities.*0\.70 rad/s.*limit', text, re.S)
    assert 'ĝ1 = 1.2 g1' in text and '20 % error' in text
    assert re.search(r'fig10_alpha.*does not converge to 1/g1', text, re.S)


def test_svg_beside_every_png(run_dir):
    for name in FIGURE_NAMES:
        png, svg = run_dir / 'figures' / f'{name}.png', run_dir / 'figures' / f'{name}.svg'
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
        root = ElementTree.parse(svg).getroot()
        assert root.tag.endswith('svg'), name


def test_every_metric_is_in_the_page_and_documented_in_the_readme(run_dir):
    metrics = json.loads((run_dir / 'metrics.json').read_text())
    flat = flatten_metrics(metrics)
    text = (run_dir / 'report.html').read_text(encoding='utf-8')
    undocumented = [k for k in flat if k not in METRIC_DOCS]
    assert not undocumented, f'add to METRIC_DOCS: {undocumented}'
    readme = (REPO_ROOT / 'README.md').read_text(encoding='utf-8')
    # Every key the tools write (including those of simulate and report only).
    missing = [k for k in METRIC_DOCS if f'`{k}`' not in readme]
    assert not missing, f'README: document the metrics keys {missing}'
    for key in flat:
        assert f'<code>{key}</code>' in text, key
    claims = re.search(r'<table id="claims">(.*?)</table>', text, re.S).group(1)
    assert claims.count('<tr>') == 11  # header + 10 claims
    assert 'class="yes"' in claims


def test_chromium_renders_the_page_with_all_figures(run_dir, chromium, tmp_path):
    # A copy of the page with a probe script: after load, each image reports whether
    # Chromium decoded it (naturalWidth) into the DOM that --dump-dom prints.
    page = (run_dir / 'report.html').read_text(encoding='utf-8')
    probe = ('<script>window.addEventListener("load", () => { for (const img of '
             'document.images) { img.setAttribute("data-decoded", img.complete && '
             'img.naturalWidth > 0 ? img.naturalWidth + "x" + img.naturalHeight : "no"); '
             '} document.body.setAttribute("data-probed", "yes"); });</script>')
    probed = tmp_path / 'probed.html'
    probed.write_text(page.replace('</body>', probe + '</body>'), encoding='utf-8')
    common = [chromium, '--headless=new', '--no-sandbox', '--disable-gpu',
              '--disable-dev-shm-usage', '--no-first-run', '--hide-scrollbars',
              f'--user-data-dir={tmp_path / "profile"}', '--virtual-time-budget=10000']
    dom = subprocess.run(common + ['--dump-dom', probed.as_uri()], capture_output=True,
                         text=True, timeout=180, check=False)
    assert 'data-probed="yes"' in dom.stdout, dom.stderr[-2000:]
    decoded = re.findall(r'<img[^>]*data-decoded="([^"]+)"', dom.stdout)
    assert len(decoded) == len(FIGURE_NAMES), decoded
    sizes = [tuple(int(v) for v in d.split('x')) for d in decoded if d != 'no']
    assert len(sizes) == len(FIGURE_NAMES), f'not decoded: {decoded}'
    assert all(w >= 500 and h >= 300 for w, h in sizes), sizes
    assert '<table id="metrics">' in dom.stdout and '<table id="claims">' in dom.stdout
    # And it draws: a screenshot of the page's top (outcome, claims, first figure).
    shot = tmp_path / 'shot.png'
    subprocess.run(common + ['--window-size=1280,2400', f'--screenshot={shot}',
                             (run_dir / 'report.html').as_uri()],
                   capture_output=True, timeout=180, check=False)
    assert shot.is_file(), 'chromium wrote no screenshot'
    import matplotlib.image
    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[0] >= 2000 and pixels.shape[1] >= 1200
    grey = pixels[..., :3].mean(axis=2)
    # Text, table shading and plot lines: a good share of the pixels is not white.
    assert np.mean(grey < 0.9) > 0.02


def test_every_limit_line_says_what_it_limits(tmp_path, monkeypatch):
    # The speed figure draws the vehicle's speed beside the ±1.5 m/s line, and the speed
    # goes past it (1.77 m/s after the push): the line limits the desired speed υ_d, and
    # its label must say so; likewise for each other limit line.
    from wip_tools.analysis import figures
    labels = []
    draw = figures._limit_lines

    def recording(ax, value, label, data=None):
        labels.append(label)
        draw(ax, value, label, data)
    monkeypatch.setattr(figures, '_limit_lines', recording)
    scenario = dataclasses.replace(Scenario(), duration=1.0)
    figures.write_figures(run_scenario(scenario).record, scenario, tmp_path)
    tg, mpc = scenario.trajectory_generator, scenario.mpc
    assert sorted(labels) == sorted([
        f'υ_d limit ±{tg.max_speed:g} m/s', f'ω_d limit ±{tg.max_yaw_rate:g} rad/s',
        f'MPC tilt limit ±{mpc.max_tilt:g} rad (soft)',
        f'per-wheel limit ±{scenario.mixer.max_wheel_torque:g} N·m',
        f'MPC limit on Δτ_υ ±{mpc.max_delta_torque:g} N·m'])
    assert 'υ_d limit ±1.5 m/s' in labels
