"""Fixtures for the studio's browser tests: one simulated daemon, one studio on it and one headless Chromium page,
shared by a test module (starting them costs tens of seconds on a loaded two-core machine).

Chromium is Debian's (``/usr/bin/chromium``, or ``LIKENESS_CHROMIUM``) driven by Playwright; WebGL runs in software
(SwiftShader through ANGLE). Without the browser or Playwright the browser tests are skipped, saying why.
Screenshots go to ``docs/images/`` when ``LIKENESS_DOC_IMAGES=1`` (to refresh the documentation), else to a
temporary folder.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"
#: Flags that give headless Chromium a working software WebGL on a machine without a GPU.
CHROMIUM_ARGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                 "--no-sandbox", "--disable-dev-shm-usage")


def chromium_path() -> str | None:
    path = os.environ.get("LIKENESS_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
    return path if Path(path).is_file() else None


def _lower_priority(name_part: str, niceness: int = 10) -> None:
    """Lower the priority of this process's descendants whose name contains ``name_part`` (Chromium's software
    WebGL would otherwise take a core from the simulated buses; its later processes inherit the niceness)."""
    import psutil

    for proc in psutil.Process().children(recursive=True):
        try:
            if name_part in proc.name().lower():
                proc.nice(max(proc.nice(), niceness))
        except psutil.Error:
            pass


def tolerant_head(path: Path) -> Any:
    """The sample head with the emulated buses' patience raised: on a loaded two-core host beside a software
    renderer, emulator answers arrive late in bursts, which real buses would not be forgiven."""
    from dataclasses import replace

    from models.headspec import load_head

    head = load_head(path)
    patience = {"canopen402": {"heartbeat_timeout_s": 5.0, "feedback_timeout_s": 5.0, "sdo_timeout_s": 5.0},
                "dynamixel": {"max_consecutive_failures": 400, "retries": 8}}
    buses = {name: replace(bus, options={**bus.options, **patience.get(bus.driver, {})})
             for name, bus in head.buses.items()}
    return replace(head, buses=buses)


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if os.environ.get("LIKENESS_DOC_IMAGES") == "1":
        out = ROOT / "docs" / "images"
        out.mkdir(parents=True, exist_ok=True)
        return out
    return tmp_path_factory.mktemp("screens")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    exe = chromium_path()
    if exe is None:
        pytest.skip("Debian's chromium is not installed (apt-get install -y chromium; .ci/run installs it)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (test extra)")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=exe, args=list(CHROMIUM_ARGS), headless=True)
        _lower_priority("chrom")
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A daemon on the sample head with its emulated buses, on free loopback ports."""
    from runtime.daemon import Daemon

    tmp = tmp_path_factory.mktemp("daemon")
    overrides = {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                 "runtime.record_dir": str(tmp / "recordings"), "safety.feedback_timeout_s": 5.0}
    d = Daemon(tolerant_head(SAMPLE), overrides)
    d.start()
    try:
        yield d
    finally:
        d.stop()


@pytest.fixture(scope="module")
def studio(daemon: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    from studio.app import Studio, StudioOptions
    from studio.head import StudioHead

    options = StudioOptions(port=0, daemon=daemon.command_endpoint, telemetry=daemon.telemetry_endpoint,
                            clips_dir=tmp_path_factory.mktemp("clips"))
    s = Studio(StudioHead.load(SAMPLE), options)
    try:
        yield s
    finally:
        s.close()


@pytest.fixture(scope="module")
def page(browser: Any, studio: Any) -> Iterator[Any]:
    """The studio's page, loaded, with its jaw slider on screen."""
    pg = browser.new_page(viewport={"width": 1200, "height": 800})
    pg.set_default_timeout(60_000)
    pg.goto(studio.url())
    pg.get_by_role("slider", name="jaw", exact=True).wait_for(state="visible", timeout=120_000)
    try:
        yield pg
    finally:
        pg.close()
