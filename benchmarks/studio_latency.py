"""Studio latency in headless Chromium: slider move → rendered skin change, where the time goes, and E-stop.

The studio runs on the sample head; Debian's Chromium (software WebGL, SwiftShader) loads its page through
Playwright. Each trial presses a key on the jaw slider (End and Home in turn: the jaw's two limits).

The figure: an in-page timeline (``TIMELINE_SCRIPT``) from the keydown through the message sent, the WebSocket frames
in viser's worker, the decoded batch with the skin on the page, the vertex uploads and the draw call after the last
of them, to the next animation frame (the frame with the new skin drawn and handed on); stages as medians and p90s.
The server's share of a move is timed in ``Studio.set_pose`` (predict, bands, verdict, send).

Cross-check and baseline, on a second page whose WebGL frames stay readable (``preserveDrawingBuffer``): from the
keydown to the first animation frame whose face pixels differ (``readPixels`` every frame, which itself costs time),
and a key on the Animate tab's time slider with an empty clip, from the keydown to the server's text reply in the
page (browser → server → browser, no mesh). With the E-stop figure (default) a simulated daemon runs in a process of
its own and the E-stop button is clicked: from the click event in the page to the daemon's ``estop`` event time
(the page's wall clock and the daemon's monotonic clock related through this process's reading of both). The goal
is ≤ 50 ms slider-to-render on the sample head.

Run: ``python benchmarks/studio_latency.py [--trials 30] [--no-estop] [--chromium-arg=--disable-gpu-vsync ...]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SAMPLE = ROOT / "heads" / "sample" / "head.toml"
GOAL_MS = 50.0
CHROMIUM_ARGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                 "--no-sandbox", "--disable-dev-shm-usage")

#: Run before the page's scripts. PRESERVE_SCRIPT (the pixel cross-check's page only): WebGL contexts keep their last
#: frame readable, which costs a copy per frame. TIMELINE_SCRIPT: a timeline of what follows a key, in
#: ``window.__ev`` as [event, performance.now(), detail]: "key" (a keydown), "send" (the page hands a message to
#: viser's WebSocket worker), "wsout"/"wsin" (WebSocket frames sent and received in that worker, stamped by a wrapper
#: worker and handed to the page with the next batch), "recv" (a decoded batch of server messages reaches the page),
#: "upload" (vertex-sized ``bufferData``/``bufferSubData``), "draw" (the first draw call after an upload) and "raf"
#: (the animation frame after that draw: the frame with the new skin has been drawn and handed on).
PRESERVE_SCRIPT = """
(() => {
  const orig = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (kind, attrs) {
    if (kind === "webgl" || kind === "webgl2") attrs = Object.assign({}, attrs || {}, {preserveDrawingBuffer: true});
    return orig.call(this, kind, attrs);
  };
})();
"""

TIMELINE_SCRIPT = """
(() => {
  const ev = window.__ev = [];
  window.__bigUpload = 1e12;  // bytes: uploads at least this large are vertex data (set by the benchmark)
  const now = () => performance.now();
  document.addEventListener("keydown", () => ev.push(["key", now(), null]), {capture: true});
  const W = window.Worker;
  const post = W.prototype.postMessage;
  W.prototype.postMessage = function (data, ...rest) {
    if (data && data.type === "send") ev.push(["send", now(), data.message && data.message.type]);
    return post.call(this, data, ...rest);
  };
  // The WebSocket lives in viser's worker: a wrapper worker stamps its frames (wall clock) and hands the stamps
  // to the page with the next decoded batch.
  const tap = `
    const stamps = [];
    const wall = () => performance.timeOrigin + performance.now();
    const send = WebSocket.prototype.send;
    WebSocket.prototype.send = function (d) { stamps.push(["wsout", wall(), 0]); return send.call(this, d); };
    const om = Object.getOwnPropertyDescriptor(WebSocket.prototype, "onmessage");
    Object.defineProperty(WebSocket.prototype, "onmessage", {configurable: true, get() { return om.get.call(this); },
      set(fn) { om.set.call(this, function (e) { stamps.push(["wsin", wall(), e.data.size || e.data.byteLength || 0]);
                                                 return fn.call(this, e); }); }});
    const post = self.postMessage.bind(self);
    self.postMessage = (d, tr) => { if (d && d.type === "message_batch") d.__stamps = stamps.splice(0);
                                    return post(d, tr); };`;
  window.Worker = class extends W {
    constructor(url, opts) {
      const module = opts && opts.type === "module";
      const src = tap + (module ? `\nimport(${JSON.stringify(String(url))});`
                                : `\nimportScripts(${JSON.stringify(String(url))});`);
      super(URL.createObjectURL(new Blob([src], {type: "text/javascript"})), opts);
      this.addEventListener("message", (e) => {
        const d = e.data;
        if (!d || d.type !== "message_batch") return;
        for (const [k, t, n] of d.__stamps || []) ev.push([k, t - performance.timeOrigin, n]);
        ev.push(["recv", now(), d.messages.map((m) => m.type + (m.name ? ":" + m.name : ""))]);
      });
    }
  };
  let armed = false;
  for (const C of [window.WebGLRenderingContext, window.WebGL2RenderingContext]) {
    if (!C) continue;
    for (const fn of ["bufferData", "bufferSubData"]) {
      const o = C.prototype[fn];
      C.prototype[fn] = function (target, data, ...rest) {
        const n = data && data.byteLength !== undefined ? data.byteLength : 0;
        if (n >= window.__bigUpload) { ev.push(["upload", now(), n]); armed = true; }
        return o.call(this, target, data, ...rest);
      };
    }
    for (const fn of ["drawElements", "drawArrays"]) {
      const o = C.prototype[fn];
      C.prototype[fn] = function (...args) {
        if (armed) {
          armed = false;
          ev.push(["draw", now(), fn]);
          requestAnimationFrame(() => ev.push(["raf", now(), null]));
        }
        return o.apply(this, args);
      };
    }
  }
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


def _p90(xs: list[float]) -> float:
    import numpy as np

    good = [x for x in xs if x >= 0]
    return float(np.percentile(good, 90)) if good else float("nan")


#: The stages of a slider move, in order, as (label, from event, to event) over :func:`_stages`' event times.
STAGES = (("key → message handed to the WebSocket worker", "key", "send"),
          ("worker → frame sent", "send", "wsout"),
          ("frame sent → skin frame received (server, loopback)", "wsout", "wsin"),
          ("worker: decompress, decode, pace → batch on the page", "wsin", "recv"),
          ("  (message handed on → skin batch on the page, all of the above)", "send", "recv"),
          ("batch → first vertex upload (viser frame clock, React commit)", "recv", "upload0"),
          ("first → last vertex upload", "upload0", "upload"),
          ("last upload → its draw call", "upload", "draw"),
          ("draw → next animation frame (frame handed on)", "draw", "raf"))


def _stages(ev: list[list]) -> dict[str, float] | None:
    """Event times (page ms) of one slider move: the key, the message out, the skin's batch back, its uploads, the
    draw after the last upload and the animation frame after that draw; None when the move did not complete."""
    def first(name: str, after: float, pred: Any = None) -> float | None:
        for e in ev:
            if e[0] == name and e[1] >= after and (pred is None or pred(e[2])):
                return float(e[1])
        return None

    out: dict[str, float] = {}
    key = first("key", -1e18)
    if key is None:
        return None
    send = first("send", key, lambda d: d == "GuiUpdateMessage")
    if send is None:
        return None
    recv = first("recv", send, lambda d: any("/skin/" in m for m in d))
    if recv is None:
        return None
    uploads = [float(e[1]) for e in ev if e[0] == "upload" and e[1] >= recv]
    if not uploads:
        return None
    draw = first("draw", uploads[-1])
    raf = first("raf", draw) if draw is not None else None
    if raf is None:
        return None
    out.update(key=key, send=send, recv=recv, upload0=uploads[0], upload=uploads[-1], draw=draw, raf=raf)
    wsout = first("wsout", send)
    if wsout is not None:  # the frame that brought the skin: the largest received between the send and the batch
        ins = [e for e in ev if e[0] == "wsin" and wsout <= e[1] <= recv]
        if ins:
            out.update(wsout=wsout, wsin=float(max(ins, key=lambda e: e[2])[1]))
    out["uploads"] = float(len(uploads))
    return out


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
    from models.client import Client, DaemonTimeout

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
    ap.add_argument("--chromium-arg", action="append", default=[],
                    help="an extra Chromium flag (repeatable), e.g. --disable-gpu-vsync")
    ap.add_argument("--viser-lighting", action="store_true",
                    help="for comparison: viser's default scene lighting (shadow-casting lights, environment map) "
                         "and shadow-casting skin meshes instead of the studio's")
    args = ap.parse_args(argv)
    if not Path(args.chromium).is_file():
        print(f"studio_latency: {args.chromium} not found (apt-get install -y chromium)")
        return 1
    import numpy as np
    from playwright.sync_api import sync_playwright

    from studio.app import Studio, StudioOptions
    from studio.head import StudioHead

    print(f"load average before: {_load_average()}")
    print(f"chromium flags: {' '.join((*CHROMIUM_ARGS, *args.chromium_arg))}")
    daemon = None if args.no_estop else _start_daemon()
    head = StudioHead.load(SAMPLE)
    studio = Studio(head, StudioOptions(port=0, daemon=daemon[1] if daemon else None,
                                        telemetry=daemon[2] if daemon else None))
    # The server's share of a page slider move: the pose handler from the pose to the flushed messages.
    set_pose, in_set_pose = studio.set_pose, []

    def timed_set_pose(*a: Any, **kw: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return set_pose(*a, **kw)
        finally:
            in_set_pose.append((time.perf_counter() - t0) * 1e3)

    studio.set_pose = timed_set_pose  # type: ignore[method-assign]
    if args.viser_lighting:
        studio.server.scene.configure_default_lights(enabled=True, cast_shadow=True)
        studio.server.scene.configure_environment_map("warehouse")
        for h in studio.view.handles:
            h.cast_shadow, h.receive_shadow = True, True
    print(f"scene lighting: {'viser default (shadows, environment map)' if args.viser_lighting else 'studio'}")
    n_vertices = head.predictor.n_vertices
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
            browser = pw.chromium.launch(executable_path=args.chromium,
                                         args=[*CHROMIUM_ARGS, *args.chromium_arg])
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            page.add_init_script(TIMELINE_SCRIPT)
            page.set_default_timeout(120_000)
            page.goto(studio.url())
            slider = page.get_by_role("slider", name="jaw", exact=True)
            slider.wait_for()
            page.wait_for_timeout(3000)
            page.evaluate(f"window.__bigUpload = {n_vertices * 12}")  # one float32 xyz per vertex
            # The page's idle frame clock: intervals between animation frames over one second.
            frame_ms = page.evaluate("""() => new Promise((resolve) => { const ts = [];
                const f = (t) => { ts.push(t); if (ts.length < 61) requestAnimationFrame(f);
                                   else resolve(ts.slice(1).map((x, i) => x - ts[i])); };
                requestAnimationFrame(f); })""")
            stages: list[dict[str, float]] = []
            incomplete = 0
            page.get_by_role("tab", name="Pose").click()
            for i in range(args.trials + 2):  # two warm-up trials
                slider.focus()
                page.wait_for_timeout(300)
                page.evaluate("window.__ev.length = 0")
                page.keyboard.press("End" if i % 2 == 0 else "Home")
                st = None
                end = time.monotonic() + 10
                while time.monotonic() < end:
                    page.wait_for_timeout(200)
                    st = _stages(page.evaluate("window.__ev"))
                    if st is not None:
                        page.wait_for_timeout(300)  # later uploads of the same move, if any
                        st = _stages(page.evaluate("window.__ev"))
                        break
                if i >= 2:
                    if st is None:
                        incomplete += 1
                    else:
                        stages.append(st)
            if args.trials and not stages:
                print("no complete move; first events of the last:", page.evaluate("window.__ev")[:40])
            page.close()
            # The pixel cross-check and the baseline, on a page of their own whose WebGL frames stay readable.
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            page.add_init_script(PRESERVE_SCRIPT)
            page.set_default_timeout(120_000)
            page.goto(studio.url())
            slider = page.get_by_role("slider", name="jaw", exact=True)
            slider.wait_for()
            page.wait_for_timeout(3000)
            render, trip = [], []
            for i in range(args.trials + 2):  # the pixel cross-check and the baseline, two warm-up trials each
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
                from models.client import Telemetry

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
    print(f"sample head: {n_vertices} vertices, {len(studio.skin.faces)} triangles; {args.trials} trials")
    print(f"page frame clock while idle: median {_median(frame_ms):.1f} ms between animation frames "
          f"(p90 {_p90(frame_ms):.1f} ms)")
    total = [s["raf"] - s["key"] for s in stages]
    print(f"in-page timeline, {len(stages)} complete moves ({incomplete} incomplete within 10 s), "
          f"median / p90 ms:")
    for label, a, b in STAGES:
        xs = [s[b] - s[a] for s in stages if a in s and b in s]
        if xs:
            print(f"  {label:<62} {_median(xs):7.1f} / {_p90(xs):7.1f}   (n={len(xs)})")
        else:
            print(f"  {label:<62}     n/a (no WebSocket timestamps from the worker)")
    if stages:
        print(f"  vertex uploads per move: median {_median([s['uploads'] for s in stages]):.0f}")
    print(f"  {'total: key → frame with the new skin drawn and handed on':<62} {_median(total):7.1f} / "
          f"{_p90(total):7.1f}   goal ≤ {GOAL_MS:.0f} ms: {'met' if _median(total) <= GOAL_MS else 'NOT met'}")
    print(f"  server: set_pose (predict, bands, verdict, send) median {_median(in_set_pose):.2f} ms "
          f"(p90 {_p90(in_set_pose):.2f} ms); SkinView.frame alone median {float(np.median(server)):.2f} ms")
    failed = sum(x < 0 for x in render) + sum(x < 0 for x in trip)
    r, b = _median(render), _median(trip)
    print(f"cross-check by pixels (readPixels every frame; {failed} without a change within 10 s):")
    print(f"  slider → face pixels changed: median {r:.1f} ms (p90 {_p90(render):.1f} ms)")
    print(f"  baseline, page round trip without a mesh (slider → server → text): median {b:.1f} ms")
    print(f"  ratio pixels / round trip: {r / b:.2f}; in-page total / round trip: {_median(total) / b:.2f}")
    if daemon is not None:
        print(f"E-stop click → daemon estop event: {estop_ms:.1f} ms (goal ≤ 100 ms)" if estop_ms is not None
              else "E-stop: no estop event within 10 s")
    print(f"load average after: {_load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
