"""Studio latency in headless Chromium: slider move → rendered skin change, against a page round trip, and E-stop.

The studio runs on the sample head; Debian's Chromium (software WebGL, SwiftShader) loads its page through
Playwright. Each trial presses a key on the jaw slider (End and Home in turn: the jaw's two limits) and measures, in
the page, from the keydown to the first animation frame whose pixels in the face region differ (the WebGL canvas is
read back with ``readPixels``; an init script asks for ``preserveDrawingBuffer`` so the last frame can be read at any
time). The baseline, in the same run and page: a key on the Animate tab's time slider with an empty clip, from the
keydown to the server's text reply appearing in the page (browser → server → browser, no mesh). The server's own
share (prediction, strain bands and verdict: ``SkinView.frame``) is timed too. With ``--estop`` (default) a
simulated daemon is started in a process of its own and the E-stop button is clicked: from the click event in the
page to the daemon's ``estop`` event time (the page's wall clock and the daemon's monotonic clock related through
this process's reading of both). Figures are medians; the goal is ≤ 50 ms slider-to-render on the sample head.

Run: ``python benchmarks/studio_latency.py [--trials 30] [--no-estop]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SAMPLE = ROOT / "heads" / "sample" / "head.toml"
GOAL_MS = 50.0
CHROMIUM_ARGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                 "--no-sandbox", "--disable-dev-shm-usage")

#: Runs before the page's scripts: WebGL contexts keep their last frame readable.
INIT_SCRIPT = """
(() => {
  const orig = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (kind, attrs) {
    if (kind === "webgl" || kind === "webgl2") attrs = Object.assign({}, attrs || {}, {preserveDrawingBuffer: true});
    return orig.call(this, kind, attrs);
  };
})();
"""

#: Arms a watcher: resolves with ms from the next keydown to the first frame whose face pixels differ.
ARM_RENDER = """
() => {
  const canvas = [...document.querySelectorAll("canvas")].sort((a, b) => b.width * b.height - a.width * a.height)[0];
  const gl = canvas.getContext("webgl2") || canvas.getContext("webgl");
  const w = Math.floor(canvas.width * 0.3), h = Math.floor(canvas.height * 0.6);
  const x = Math.floor(canvas.width * 0.35), y = Math.floor(canvas.height * 0.2);
  const buf = new Uint8Array(w * h * 4);
  const sig = () => { gl.readPixels(x, y, w, h, gl.RGBA, gl.UNSIGNED_BYTE, buf); let s = 0;
                      for (let i = 0; i < buf.length; i += 4) s = (s * 31 + buf[i] + 7 * buf[i + 1]) | 0; return s; };
  const before = sig();
  window.__lat = new Promise((resolve) => {
    document.addEventListener("keydown", () => {
      const t0 = performance.now();
      const poll = () => {
        if (sig() !== before) resolve(performance.now() - t0);
        else if (performance.now() - t0 > 10000) resolve(-1);
        else requestAnimationFrame(poll);
      };
      requestAnimationFrame(poll);
    }, {once: true, capture: true});
  });
}
"""

#: Arms a watcher: resolves with ms from the next keydown to the next change of the page's text.
ARM_TEXT = """
() => {
  window.__lat = new Promise((resolve) => {
    document.addEventListener("keydown", () => {
      const t0 = performance.now();
      const obs = new MutationObserver((records) => {
        if (records.some((r) => r.target.nodeType === 3 ? /^t = /.test(r.target.data)
                                                       : /^t = /.test(r.target.textContent || ""))) {
          obs.disconnect(); resolve(performance.now() - t0);
        }
      });
      obs.observe(document.body, {subtree: true, childList: true, characterData: true});
      setTimeout(() => { obs.disconnect(); resolve(-1); }, 10000);
    }, {once: true, capture: true});
  });
}
"""


def _median(xs: list[float]) -> float:
    good = [x for x in xs if x >= 0]
    return statistics.median(good) if good else float("nan")


def _load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_daemon() -> tuple[subprocess.Popen, str, str]:
    """``likeness daemon`` on the sample head in a process of its own (as in a show), on free loopback ports."""
    from runtime.client import Client, DaemonTimeout

    cmd_ep, tel_ep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "likeness.cli", "daemon", "--config", str(SAMPLE), "--command",
                             cmd_ep, "--telemetry", tel_ep, "--no-realtime"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    end = time.monotonic() + 120
    while time.monotonic() < end:
        try:
            with Client(cmd_ep, timeout=2) as c:
                c.call("hello")
            return proc, cmd_ep, tel_ep
        except DaemonTimeout:
            if proc.poll() is not None:
                break
    proc.terminate()
    raise RuntimeError("the daemon did not answer within 120 s")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--no-estop", action="store_true", help="skip the E-stop figure (no daemon started)")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args = ap.parse_args(argv)
    if not Path(args.chromium).is_file():
        print(f"studio_latency: {args.chromium} not found (apt-get install -y chromium)")
        return 1
    import numpy as np
    from playwright.sync_api import sync_playwright

    from studio.app import Studio, StudioOptions
    from studio.head import StudioHead

    print(f"load average before: {_load_average()}")
    daemon = None if args.no_estop else _start_daemon()
    head = StudioHead.load(SAMPLE)
    studio = Studio(head, StudioOptions(port=0, daemon=daemon[1] if daemon else None,
                                        telemetry=daemon[2] if daemon else None))
    try:
        # The server's share: one pose's prediction, strain bands and verdict.
        jaw = head.names.index("jaw")
        poses = [head.neutral.copy(), head.neutral.copy()]
        poses[1][jaw] = head.hi[jaw]
        server = []
        for i in range(100):
            t0 = time.perf_counter()
            studio.skin.frame(poses[i % 2])
            server.append((time.perf_counter() - t0) * 1e3)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=args.chromium, args=list(CHROMIUM_ARGS))
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            page.add_init_script(INIT_SCRIPT)
            page.set_default_timeout(120_000)
            page.goto(studio.url())
            slider = page.get_by_role("slider", name="jaw", exact=True)
            slider.wait_for()
            page.wait_for_timeout(3000)
            render, trip = [], []
            for i in range(args.trials + 2):  # two warm-up trials each
                page.get_by_role("tab", name="Pose").click()
                slider.focus()
                page.wait_for_timeout(300)
                page.evaluate(ARM_RENDER)
                page.keyboard.press("End" if i % 2 == 0 else "Home")
                ms = page.evaluate("window.__lat")
                if i >= 2:
                    render.append(ms)
                page.get_by_role("tab", name="Animate").click()
                time_slider = page.get_by_role("slider", name="Time (s)", exact=True)
                time_slider.focus()
                page.wait_for_timeout(300)
                page.evaluate(ARM_TEXT)
                page.keyboard.press("End" if i % 2 == 0 else "Home")
                ms = page.evaluate("window.__lat")
                if i >= 2:
                    trip.append(ms)
            estop_ms = None
            if daemon is not None:
                from runtime.client import Telemetry

                with Telemetry(daemon[2]) as tel:
                    time.sleep(0.5)
                    page.evaluate("document.addEventListener('click', () => { window.__click = "
                                  "performance.timeOrigin + performance.now(); }, {once: true, capture: true})")
                    page.get_by_role("button", name="E-stop", exact=True).click()
                    ev = tel.wait_for(lambda topic, m: topic == "event" and m.get("event") == "estop", 10.0)
                    clicked = page.evaluate("window.__click") / 1e3  # wall clock, s
                if ev is not None:
                    wall_minus_mono = time.time() - time.monotonic()
                    estop_ms = (ev[1]["t"] + wall_minus_mono - clicked) * 1e3
            browser.close()
    finally:
        studio.close()
        if daemon is not None:
            daemon[0].terminate()
            daemon[0].wait(timeout=30)
    failed = sum(x < 0 for x in render) + sum(x < 0 for x in trip)
    r, b, s = _median(render), _median(trip), float(np.median(server))
    print(f"sample head: {head.predictor.n_vertices} vertices, {len(studio.skin.faces)} triangles; "
          f"{args.trials} trials; {failed} without a change within 10 s")
    p90 = float(np.percentile([x for x in render if x >= 0] or [np.nan], 90))
    print(f"slider → rendered skin change: median {r:.1f} ms (p90 {p90:.1f} ms); goal ≤ {GOAL_MS:.0f} ms: "
          f"{'met' if r <= GOAL_MS else 'NOT met'}")
    print(f"baseline, page round trip without a mesh (slider → server → text): median {b:.1f} ms")
    print(f"ratio render / round trip: {r / b:.2f}")
    print(f"server share (predict + strain bands + verdict): median {s:.2f} ms")
    if daemon is not None:
        print(f"E-stop click → daemon estop event: {estop_ms:.1f} ms (goal ≤ 100 ms)" if estop_ms is not None
              else "E-stop: no estop event within 10 s")
    print(f"load average after: {_load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
