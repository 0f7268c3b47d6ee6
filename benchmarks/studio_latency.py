"""Studio latency in headless Chromium: slider move → skin drawn, for the face view against the old path, and where
the time goes.

Two studios run on the sample head: the face view (the default: the page owns a three.js mesh of the subdivided
skin and writes each frame's vertex positions and colours into it from the studio's own WebSocket) and the old path
(``--skin-view bands``: the simulation triangles as viser scene meshes per strain band, rebuilt by viser's client on
every update). One page is open at a time, in blocks that alternate between the two (``--rounds``), so both see the
same machine load. Each trial presses a key on the jaw slider (End and Home in turn: the jaw's two limits).

The figure: an in-page timeline (``TIMELINE_SCRIPT``, plus the face view's own stamps: buffer received, written into
the mesh, and the studio's own stamps) from the keydown through the message sent, the skin arriving, the vertex
uploads and the draw call after the last of them, to the later of the next animation frame and one pixel read back
after the draw (which returns when the software renderer has drawn the frame with the new skin); stages as medians
and p90s. Goal: face view ≤ 50 ms median and ≤ 80 ms p90; the ratio old / face is printed from the same run.
Cross-check, on pages whose WebGL frames stay readable (``preserveDrawingBuffer``): from the keydown to the first
animation frame whose face pixels differ (``readPixels`` every frame, which itself costs time); and a baseline page
round trip without a mesh (a key on the Animate tab's time slider to the server's text reply). With the E-stop
figure (default) a simulated daemon runs in a process of its own and the E-stop button is clicked: from the click
event in the page to the daemon's ``estop`` event time.

Run: ``python benchmarks/studio_latency.py [--trials 30] [--rounds 2] [--subdivisions 1] [--no-estop]``.
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
GOAL_P90_MS = 80.0
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
      C.prototype[fn] = function (...args) {  // bufferData(target, data, ...), bufferSubData(target, offset, data, ...)
        const data = args[fn === "bufferData" ? 1 : 2];
        const n = data && data.byteLength !== undefined ? data.byteLength : 0;
        if (n >= window.__bigUpload) { ev.push(["upload", now(), n]); armed = true; }
        return o.apply(this, args);
      };
    }
    for (const fn of ["drawElements", "drawArrays"]) {
      const o = C.prototype[fn];
      C.prototype[fn] = function (...args) {
        if (armed) {
          armed = false;
          ev.push(["draw", now(), fn]);
          requestAnimationFrame(() => ev.push(["raf", now(), null]));
          // Once the present task has issued the whole frame, one pixel read back: it returns when the renderer
          // (SwiftShader, on the CPU) has executed every command before it, i.e. drawn the frame with the new skin.
          const gl = this;
          setTimeout(() => {
            gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
            ev.push(["gpu", now(), null]);
          }, 0);
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
    window.addEventListener("keydown", () => {
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
    window.addEventListener("keydown", () => {
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


#: The stages of a slider move per skin view, in order, as (label, from event, to event) over :func:`_stages`' times.
STAGES = {
    "bands": (("key → message handed to the WebSocket worker", "key", "send"),
              ("worker → frame sent", "send", "wsout"),
              ("frame sent → skin frame received (server, loopback)", "wsout", "wsin"),
              ("worker: decompress, decode, pace → batch on the page", "wsin", "recv"),
              ("  (message handed on → skin batch on the page, all of the above)", "send", "recv"),
              ("batch → first vertex upload (viser frame clock, React commit)", "recv", "upload0"),
              ("first → last vertex upload", "upload0", "upload"),
              ("last upload → its draw call", "upload", "draw"),
              ("draw → next animation frame", "draw", "raf"),
              ("draw → the renderer has drawn it (a pixel read back)", "draw", "gpu")),
    "face": (("key → slider value sent on the studio's socket", "key", "send"),
             ("value sent → the studio has it (loopback, its socket thread)", "send", "srv_in"),
             ("studio: pose, strain, fine surface → frame offered to the page", "srv_in", "srv_frame"),
             ("frame offered → skin buffer received (sender thread, page)", "srv_frame", "recv"),
             ("  (value sent → skin buffer received, all of the above)", "send", "recv"),
             ("buffer → written into the page's mesh (normals recomputed)", "recv", "applied"),
             ("written → first vertex upload (drawn at once)", "applied", "upload0"),
             ("first → last vertex upload", "upload0", "upload"),
             ("last upload → its draw call", "upload", "draw"),
             ("draw → next animation frame", "draw", "raf"),
             ("draw → the renderer has drawn it (a pixel read back)", "draw", "gpu")),
}
#: The figure's end: the frame with the new skin drawn by the renderer (a pixel read back after the draw returns) and
#: the page's next animation frame begun, whichever is later.
DONE = "done"


def _stages(ev: list[list], view: str) -> dict[str, float] | None:
    """Event times (page ms) of one slider move: the key, the message out, the skin back (viser's batch, or the
    studio socket's buffer and its write into the mesh), its uploads, the draw after the last upload and the
    animation frame after that draw; None when the move did not complete."""
    def first(name: str, after: float, pred: Any = None) -> float | None:
        for e in ev:
            if e[0] == name and e[1] >= after and (pred is None or pred(e[2])):
                return float(e[1])
        return None

    out: dict[str, float] = {}
    key = first("key", -1e18)
    if key is None:
        return None
    # The face view's page sends the value on the studio's own socket ("fastsend"); viser's copy follows later.
    send = first("fastsend", key) if view == "face" else None
    if send is None:
        send = first("send", key, lambda d: d == "GuiUpdateMessage")
    if send is None:
        return None
    if view == "face":
        recv = first("skinrecv", send)
        applied = first("skin", recv) if recv is not None else None
        if applied is None:
            return None
        out["applied"] = applied
    else:
        recv = first("recv", send, lambda d: any("/skin/" in m for m in d))
    if recv is None:
        return None
    uploads = [float(e[1]) for e in ev if e[0] == "upload" and e[1] >= recv]
    if not uploads:
        return None
    draw = first("draw", uploads[-1])
    raf = first("raf", draw) if draw is not None else None
    gpu = first("gpu", draw) if draw is not None else None
    if raf is None or gpu is None:
        return None
    out.update(key=key, send=send, recv=recv, upload0=uploads[0], upload=uploads[-1], draw=draw, raf=raf, gpu=gpu,
               done=max(raf, gpu))
    srv = [e for e in ev if e[0] == "srv_in" and e[1] >= send - 5.0]  # the studio's stamps (its wall clock)
    if view == "face" and srv:
        out["srv_in"] = float(srv[0][1])
        frames = [float(e[1]) for e in ev if e[0] == "srv_frame" and e[1] >= out["srv_in"]]
        if frames:
            out["srv_frame"] = frames[0]
    wsout = first("wsout", send)
    if view == "bands" and wsout is not None:  # the frame that brought the skin: the largest between send and batch
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


def _open(browser: Any, url: str, script: str) -> Any:
    page = browser.new_page(viewport={"width": 1200, "height": 800})
    page.add_init_script(script)
    page.set_default_timeout(120_000)
    page.goto(url)
    page.get_by_role("slider", name="jaw", exact=True).wait_for()
    page.wait_for_timeout(3000)
    page.get_by_role("tab", name="Pose").click()
    return page


def _moves(page: Any, view: str, upload_bytes: int, trials: int, first: int,
           server: list[tuple[str, float]]) -> tuple[list[dict], int]:
    """``trials`` jaw moves (End, Home in turn) on a page with the timeline script; their stages and how many did
    not complete within 10 s. ``server`` collects the studio's own stamps (name, wall-clock s), merged into the
    page's timeline through the page's time origin."""
    page.evaluate(f"window.__bigUpload = {upload_bytes}")
    origin_ms = float(page.evaluate("performance.timeOrigin"))
    slider = page.get_by_role("slider", name="jaw", exact=True)
    out, incomplete = [], 0

    def timeline() -> list[list]:
        return page.evaluate("window.__ev") + [[n, t * 1e3 - origin_ms, None] for n, t in list(server)]

    for i in range(first, first + trials):
        slider.focus()
        page.wait_for_timeout(300)
        page.evaluate("window.__ev.length = 0")
        server.clear()
        page.keyboard.press("End" if i % 2 == 0 else "Home")
        st = None
        end = time.monotonic() + 10
        while time.monotonic() < end:
            page.wait_for_timeout(150)
            st = _stages(timeline(), view)
            if st is not None:
                page.wait_for_timeout(250)  # later uploads of the same move, if any
                st = _stages(timeline(), view)
                break
        if st is None:
            incomplete += 1
        else:
            out.append(st)
    return out, incomplete


def _pixels(page: Any, trials: int, first: int) -> list[float]:
    """Key → first frame whose face pixels differ, on a page whose WebGL frames stay readable."""
    slider = page.get_by_role("slider", name="jaw", exact=True)
    out = []
    for i in range(first, first + trials):
        slider.focus()
        page.wait_for_timeout(300)
        page.evaluate(ARM_RENDER)
        page.keyboard.press("End" if i % 2 == 0 else "Home")
        out.append(page.evaluate("window.__lat"))
    return out


def _round_trip(page: Any, trials: int) -> list[float]:
    """The baseline: a key on the Animate tab's time slider (empty clip) to the server's text reply in the page."""
    page.get_by_role("tab", name="Animate").click()
    time_slider = page.get_by_role("slider", name="Time (s)", exact=True)
    out = []
    for i in range(trials):
        time_slider.focus()
        page.wait_for_timeout(300)
        page.evaluate(ARM_TEXT)
        page.keyboard.press("End" if i % 2 == 0 else "Home")
        out.append(page.evaluate("window.__lat"))
    page.get_by_role("tab", name="Pose").click()
    return out


def _estop_ms(browser: Any, url: str, telemetry: str) -> float | None:
    """E-stop click in the page → the daemon's ``estop`` event (page wall clock against the daemon's monotonic one
    through this process's reading of both)."""
    from models.client import Telemetry

    page = _open(browser, url, "")
    try:
        with Telemetry(telemetry) as tel:
            time.sleep(0.5)
            page.evaluate("document.addEventListener('click', () => { window.__click = "
                          "performance.timeOrigin + performance.now(); }, {once: true, capture: true})")
            page.get_by_role("button", name="E-stop", exact=True).click()
            ev = tel.wait_for(lambda topic, m: topic == "event" and m.get("event") == "estop", 10.0)
            clicked = page.evaluate("window.__click") / 1e3
    finally:
        page.close()
    if ev is None:
        return None
    return (ev[1]["t"] + time.time() - time.monotonic() - clicked) * 1e3


def _report(view: str, label: str, stages: list[dict], incomplete: int, pixels: list[float]) -> float:
    total = [s[DONE] - s["key"] for s in stages]
    print(f"{label}: {len(stages)} complete moves ({incomplete} incomplete within 10 s), median / p90 ms:")
    for name, a, b in STAGES[view]:
        xs = [s[b] - s[a] for s in stages if a in s and b in s]
        text = f"{_median(xs):7.1f} / {_p90(xs):7.1f}   (n={len(xs)})" if xs else "    n/a"
        print(f"  {name:<66} {text}")
    if stages:
        print(f"  vertex-sized uploads per move: median {_median([s['uploads'] for s in stages]):.0f}")
    raf = [s["raf"] - s["key"] for s in stages]
    print(f"  {'  (key → next animation frame after the draw, the renderer not waited for)':<66} {_median(raf):7.1f} / "
          f"{_p90(raf):7.1f}")
    print(f"  {'total: key → frame with the new skin drawn and the next frame begun':<66} {_median(total):7.1f} / "
          f"{_p90(total):7.1f}")
    fails = sum(x < 0 for x in pixels)
    print(f"  cross-check, key → face pixels changed (readPixels every frame; {fails} unchanged within 10 s): "
          f"{_median(pixels):.1f} / {_p90(pixels):.1f}")
    return _median(total)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; with ``--record``, the report is also written (atomically) to a file."""
    from benchmarks._record import captured, write_report

    args_list = sys.argv[1:] if argv is None else argv
    with captured() as out:
        rc = _run(args_list)
    record = next((Path(a.split("=", 1)[1]) for a in args_list if a.startswith("--record=")), None)
    if "--record" in args_list:
        record = Path(args_list[args_list.index("--record") + 1])
    if record is not None and rc == 0:
        import hashlib

        from models.headspec import load_head

        predictor = Path(str(load_head(SAMPLE).paths.get("predictor", "predictor.onnx")))
        inputs = [SAMPLE, predictor if predictor.is_absolute() else SAMPLE.parent / predictor]
        hashes = " ".join(f"{p.name}:{hashlib.sha256(p.read_bytes()).hexdigest()[:16]}" for p in inputs if p.is_file())
        write_report(record, f"# python benchmarks/studio_latency.py {' '.join(args_list)}\n# inputs (sha256): "
                     f"{hashes}\n", out.getvalue())
    return rc


def _run(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=30, help="moves per skin view (and pixel cross-checks)")
    ap.add_argument("--rounds", type=int, default=2, help="blocks per view, alternating face and bands")
    ap.add_argument("--subdivisions", type=int, default=1, help="Loop subdivisions of the face view")
    ap.add_argument("--no-estop", action="store_true", help="skip the E-stop figure (no daemon started)")
    ap.add_argument("--record", type=Path, default=None,
                    help="also write the report (with the command, settings and input hashes) to this file")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    ap.add_argument("--chromium-arg", action="append", default=[],
                    help="an extra Chromium flag (repeatable), e.g. --disable-gpu-vsync")
    args = ap.parse_args(argv)
    if not Path(args.chromium).is_file():
        print(f"studio_latency: {args.chromium} not found (apt-get install -y chromium)")
        return 1
    from playwright.sync_api import sync_playwright

    from studio.app import Studio, StudioOptions
    from studio.head import StudioHead

    print(f"load average before: {_load_average()}")
    print(f"chromium flags: {' '.join((*CHROMIUM_ARGS, *args.chromium_arg))}")
    daemon = None if args.no_estop else _start_daemon()
    head = StudioHead.load(SAMPLE)
    studios = {view: Studio(head, StudioOptions(port=0, skin_view=view, subdivisions=args.subdivisions,
                                                daemon=daemon[1] if daemon else None,
                                                telemetry=daemon[2] if daemon else None))
               for view in ("face", "bands")}
    in_set_pose: dict[str, list[float]] = {v: [] for v in studios}
    for view, studio in studios.items():
        def timed(*a: Any, _f: Any = studio.set_pose, _v: str = view, **kw: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return _f(*a, **kw)
            finally:
                in_set_pose[_v].append((time.perf_counter() - t0) * 1e3)

        studio.set_pose = timed  # type: ignore[method-assign]
    server: list[tuple[str, float]] = []  # the face studio's stamps: a slider value in, the frame offered
    face = studios["face"]
    slider_route, offer = face.socket._routes["slider"], face.socket.send_frame

    def slider_in(request: dict, reply: Any) -> None:
        server.append(("srv_in", time.time()))
        slider_route(request, reply)

    def frame_out(message: bytes, **kw: Any) -> None:
        server.append(("srv_frame", time.time()))
        offer(message, **kw)

    face.socket._routes["slider"] = slider_in
    face.socket.send_frame = frame_out  # type: ignore[method-assign]
    n_fine = studios["face"].view.sub.n_vertices  # type: ignore[union-attr]
    upload_bytes = {"face": n_fine * 12, "bands": head.predictor.n_vertices * 12}  # float32 xyz per vertex
    stages: dict[str, list[dict]] = {v: [] for v in studios}
    incomplete = dict.fromkeys(studios, 0)
    pixels: dict[str, list[float]] = {v: [] for v in studios}
    per_round = max(1, args.trials // max(args.rounds, 1))
    estop_ms = None
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=args.chromium, args=[*CHROMIUM_ARGS, *args.chromium_arg])
            for r in range(args.rounds):
                for view in (("face", "bands") if r % 2 == 0 else ("bands", "face")):  # one page open at a time
                    page = _open(browser, studios[view].url(), TIMELINE_SCRIPT)
                    _moves(page, view, upload_bytes[view], 2, 0, server)  # warm-up
                    got, bad = _moves(page, view, upload_bytes[view], per_round, 0, server)
                    stages[view] += got
                    incomplete[view] += bad
                    page.close()
                    page = _open(browser, studios[view].url(), PRESERVE_SCRIPT)
                    _pixels(page, 2, 0)
                    pixels[view] += _pixels(page, per_round, 0)
                    if view == "face" and r == 0:
                        trip = _round_trip(page, per_round)
                    page.close()
            if daemon is not None:
                estop_ms = _estop_ms(browser, studios["face"].url(), daemon[2])
            browser.close()
    finally:
        for studio in studios.values():
            studio.close()
        if daemon is not None:
            daemon[0].terminate()
            daemon[0].wait(timeout=30)
    print(f"sample head: {head.predictor.n_vertices} simulated vertices, {len(studios['face'].skin.faces)} "
          f"triangles; face view: {args.subdivisions} Loop subdivisions, {n_fine} vertices; "
          f"{args.rounds} rounds of {per_round} moves per view, alternating")
    new = _report("face", "FACE VIEW (page-owned mesh, one binary buffer per frame)", stages["face"],
                  incomplete["face"], pixels["face"])
    old = _report("bands", "OLD PATH (viser scene meshes per strain band)", stages["bands"], incomplete["bands"],
                  pixels["bands"])
    total = [s[DONE] - s["key"] for s in stages["face"]]
    med, p90 = _median(total), _p90(total)
    for view in studios:
        print(f"server: set_pose ({view}) median {_median(in_set_pose[view]):.2f} ms "
              f"(p90 {_p90(in_set_pose[view]):.2f} ms)")
    print(f"baseline, page round trip without a mesh (slider → server → text): median {_median(trip):.1f} ms")
    print(f"RESULT face view key → frame drawn: median {med:.1f} ms (goal ≤ {GOAL_MS:.0f}: "
          f"{'met' if med <= GOAL_MS else 'NOT met'}), p90 {p90:.1f} ms (goal ≤ {GOAL_P90_MS:.0f}: "
          f"{'met' if p90 <= GOAL_P90_MS else 'NOT met'}); old path median {old:.1f} ms; old / face {old / new:.2f}")
    if daemon is not None:
        print(f"E-stop click → daemon estop event: {estop_ms:.1f} ms" if estop_ms is not None
              else "E-stop: no estop event within 10 s")
    print(f"load average after: {_load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
