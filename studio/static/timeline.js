// Likeness Studio: the timeline editor, docked under the 3D view while the Animate tab is open.
//
// Every keyed channel is a track (a row from the channel's lower to its upper limit) with its curve as the daemon
// plays it (sampled by the server) and its keys. Keys drag in time and value; the selected key of a Bezier track
// shows its two handles, which drag too (in ≤ 0 ≤ out in time, as the clip schema requires). Keys are buttons named
// "<channel> key <n>" and handles "<channel> key <n> in handle" / "out handle": arrows move a focused key a frame
// (left, right) or a hundredth of its range (up, down), Delete removes it. Undo and Redo (also Ctrl+Z, Ctrl+Shift+Z)
// step through edits. An audio file (WAV, MP3) loads into the browser, shows its waveform and plays from the
// playhead: its clock drives the preview (the page sends the clip time it plays, the skin follows), and with "Play
// on head" the clip starts on the daemon at a scheduled time and the sound the same moment in the page.
// The server is the document's owner: every edit is a request over the studio socket (window.Likeness) and the
// view redraws from the state it publishes.
(function () {
  "use strict";
  const NS = "http://www.w3.org/2000/svg";
  const FRAME = 1 / 30, LABEL_W = 150, RULER_H = 22, AUDIO_H = 54, ROW_H = 58, PAD = 7, HEIGHT = 250;
  const L = window.Likeness;
  if (!L) return;
  let state = null, playhead = 0, drag = null, playing = null, lastTick = 0, root = null, svg = null;
  let playheadLine = null, timeText = null, statusText = null, undoButton = null, redoButton = null;
  let headBox = null, playButton = null;
  const audio = {buffer: null, name: null, peaks: null};
  let actx = null, source = null;
  const T = L.timeline = {audio, get state() { return state; }, get playhead() { return playhead; },
                          get playing() { return playing; }, lastPlay: null};

  function el(tag, attrs, parent, ns) {
    const e = ns === false ? document.createElement(tag) : document.createElementNS(NS, tag);
    for (const k in attrs || {}) e.setAttribute(k, attrs[k]);
    if (parent) parent.appendChild(e);
    return e;
  }
  function button(label, onClick, parent) {
    const b = el("button", {type: "button"}, parent, false);
    b.textContent = label;
    b.style.cssText = "margin-right:6px;padding:2px 9px;font:inherit;cursor:pointer";
    b.addEventListener("click", onClick);
    return b;
  }

  // ------------------------------------------------------------------ geometry
  function width() { return svg ? svg.clientWidth || root.clientWidth : 800; }
  function length() { return state ? state.length : 2; }
  function xOf(t) { return LABEL_W + (t / length()) * (width() - LABEL_W - 14); }
  function tOf(x) { return Math.max(0, (x - LABEL_W) / (width() - LABEL_W - 14) * length()); }
  function audioH() { return audio.buffer ? AUDIO_H : 0; }
  function rowTop(i) { return RULER_H + audioH() + i * ROW_H; }
  function yOf(tr, row, v) { const s = tr.hi > tr.lo ? tr.hi - tr.lo : 1;
                             return rowTop(row) + ROW_H - PAD - (v - tr.lo) / s * (ROW_H - 2 * PAD); }
  function vOf(tr, row, y) { const s = tr.hi > tr.lo ? tr.hi - tr.lo : 1;
                             return tr.lo + (rowTop(row) + ROW_H - PAD - y) / (ROW_H - 2 * PAD) * s; }
  function point(e) { const r = svg.getBoundingClientRect(); return [e.clientX - r.left, e.clientY - r.top]; }
  const round = (x, d) => Math.round(x * d) / d;

  // ------------------------------------------------------------------ drawing
  function render() {
    if (!svg || !state) return;
    const focused = document.activeElement && svg.contains(document.activeElement);
    const w = width(), tracks = state.tracks;
    const h = rowTop(tracks.length) + 4;
    svg.setAttribute("height", String(Math.max(h, 60)));
    svg.textContent = "";
    const ruler = el("g", {}, svg);
    el("rect", {x: 0, y: 0, width: w, height: RULER_H, fill: "#eef0f3", "data-scrub": "1"}, ruler);
    const step = niceStep(length() / Math.max(1, (w - LABEL_W) / 70));
    for (let t = 0; t <= length() + 1e-9; t += step) {
      el("line", {x1: xOf(t), x2: xOf(t), y1: RULER_H - 6, y2: h, stroke: "#e2e4e8"}, ruler);
      const tx = el("text", {x: xOf(t) + 2, y: 14, "font-size": 10, fill: "#555", "pointer-events": "none"}, ruler);
      tx.textContent = round(t, 1000) + " s";
    }
    if (audio.buffer) drawAudio();
    tracks.forEach((tr, row) => drawTrack(tr, row));
    playheadLine = el("line", {y1: 0, y2: h, stroke: "#d33", "stroke-width": 1.5, "pointer-events": "none"}, svg);
    movePlayhead(playhead);
    if (undoButton) { undoButton.disabled = !state.can_undo; redoButton.disabled = !state.can_redo; }
    if (headBox) headBox.disabled = !state.head;
    if (focused && state.selected) {
      const k = svg.querySelector('[data-key="' + CSS.escape(state.selected[0] + "/" + state.selected[1]) + '"]');
      if (k) k.focus();
    }
  }

  function niceStep(raw) {
    const p = Math.pow(10, Math.floor(Math.log10(raw || 1)));
    for (const m of [1, 2, 5, 10]) if (m * p >= raw) return m * p;
    return 10 * p;
  }

  function drawAudio() {
    const g = el("g", {role: "img", "aria-label": "Waveform of " + audio.name}, svg);
    const top = RULER_H, mid = top + AUDIO_H / 2, amp = AUDIO_H / 2 - 4;
    el("rect", {x: 0, y: top, width: width(), height: AUDIO_H, fill: "#f7f3ea"}, g);
    const label = el("text", {x: 6, y: top + 16, "font-size": 11, fill: "#333"}, g);
    label.textContent = "♪ " + audio.name;
    const d = [];
    const n = audio.peaks.length / 2, dur = audio.buffer.duration;
    for (let i = 0; i < n; i++) {
      const x = xOf(dur * i / n).toFixed(1);
      d.push("M" + x + " " + (mid - audio.peaks[2 * i + 1] * amp).toFixed(1) + "V" +
             (mid - audio.peaks[2 * i] * amp + 0.5).toFixed(1));
    }
    el("path", {d: d.join(""), stroke: "#b07a1c", "stroke-width": 1, fill: "none", "data-scrub": "1"}, g);
  }

  function drawTrack(tr, row) {
    const g = el("g", {role: "group", "aria-label": "Track " + tr.name}, svg);
    const top = rowTop(row);
    el("rect", {x: 0, y: top, width: width(), height: ROW_H, fill: row % 2 ? "#fafbfc" : "#ffffff",
                "data-scrub": "1"}, g);
    el("line", {x1: 0, x2: width(), y1: top + ROW_H, y2: top + ROW_H, stroke: "#e5e7eb"}, g);
    const name = el("text", {x: 6, y: top + 20, "font-size": 12, fill: "#222"}, g);
    name.textContent = tr.name;
    const sub = el("text", {x: 6, y: top + 36, "font-size": 10, fill: "#777"}, g);
    sub.textContent = tr.interp + " · " + round(tr.lo, 100) + "…" + round(tr.hi, 100);
    const pts = tr.curve.t.map((t, i) => xOf(t).toFixed(1) + "," + yOf(tr, row, tr.curve.v[i]).toFixed(1));
    el("polyline", {points: pts.join(" "), fill: "none", stroke: "#1f77b4", "stroke-width": 1.6,
                    "pointer-events": "none"}, g);
    tr.keys.forEach((k, i) => {
      const sel = state.selected && state.selected[0] === tr.name && state.selected[1] === i;
      if (sel && tr.interp === "bezier") drawHandles(g, tr, row, i, k);
      const c = el("circle", {cx: xOf(k[0]), cy: yOf(tr, row, k[1]), r: sel ? 6.5 : 5,
                              fill: sel ? "#ff7f0e" : "#d62728", stroke: "#fff", "stroke-width": 1.5,
                              role: "button", tabindex: 0, "data-key": tr.name + "/" + i,
                              "aria-label": tr.name + " key " + (i + 1),
                              "aria-description": "at " + round(k[0], 1000) + " s, value " + round(k[1], 10000)}, g);
      c.style.cursor = "grab";
      c.addEventListener("pointerdown", (e) => startDrag(e, {kind: "key", tr, row, i, k, node: c}));
      c.addEventListener("keydown", (e) => keyKeys(e, tr, i, k));
    });
  }

  function drawHandles(g, tr, row, i, k) {
    const [t, v, inDt, inDv, outDt, outDv] = k;
    const kx = xOf(t), ky = yOf(tr, row, v);
    for (const [side, dt, dv] of [["in", inDt, inDv], ["out", outDt, outDv]]) {
      const hx = xOf(t + dt), hy = yOf(tr, row, v + dv);
      const line = el("line", {x1: kx, y1: ky, x2: hx, y2: hy, stroke: "#888", "stroke-width": 1,
                               "pointer-events": "none"}, g);
      const h = el("circle", {cx: hx, cy: hy, r: 4.5, fill: "#fff", stroke: "#555", "stroke-width": 1.5,
                              role: "button", tabindex: 0, "aria-label": tr.name + " key " + (i + 1) + " " + side +
                              " handle"}, g);
      h.style.cursor = "grab";
      h.addEventListener("pointerdown", (e) => startDrag(e, {kind: side, tr, row, i, k, node: h, line}));
    }
  }

  function movePlayhead(t) {
    playhead = t = Math.min(Math.max(t, 0), Math.max(length(), audio.buffer ? audio.buffer.duration : 0));
    if (playheadLine) { const x = xOf(t); playheadLine.setAttribute("x1", x); playheadLine.setAttribute("x2", x); }
    if (timeText) timeText.textContent = "t = " + t.toFixed(2) + " s";
  }

  // ------------------------------------------------------------------ editing
  function startDrag(e, d) {
    e.preventDefault();
    e.stopPropagation();
    d.node.setPointerCapture(e.pointerId);
    d.start = point(e);
    d.moved = false;
    drag = d;
    d.node.focus();
    d.node.addEventListener("pointermove", onDrag);
    d.node.addEventListener("pointerup", endDrag, {once: true});
  }

  function dragged(d, p) {
    const t = tOf(p[0]), v = Math.min(d.tr.hi, Math.max(d.tr.lo, vOf(d.tr, d.row, p[1])));
    if (d.kind === "key") return {t: round(t, 1000), v: round(v, 1e6)};
    const [kt, kv] = d.k;
    let dt = t - kt;
    dt = d.kind === "in" ? Math.min(0, dt) : Math.max(0, dt);
    return {dt: round(dt, 1e6), dv: round(vOf(d.tr, d.row, p[1]) - kv, 1e6)};
  }

  function onDrag(e) {
    const d = drag;
    if (!d) return;
    const p = point(e);
    if (Math.abs(p[0] - d.start[0]) + Math.abs(p[1] - d.start[1]) > 2) d.moved = true;
    if (!d.moved) return;
    const m = dragged(d, p);
    if (d.kind === "key") {
      d.node.setAttribute("cx", xOf(m.t));
      d.node.setAttribute("cy", yOf(d.tr, d.row, m.v));
      status("Key at " + m.t.toFixed(3) + " s, value " + round(m.v, 1e4));
    } else {
      const x = xOf(d.k[0] + m.dt), y = yOf(d.tr, d.row, d.k[1] + m.dv);
      d.node.setAttribute("cx", x); d.node.setAttribute("cy", y);
      d.line.setAttribute("x2", x); d.line.setAttribute("y2", y);
    }
  }

  function endDrag(e) {
    const d = drag;
    drag = null;
    if (!d) return;
    d.node.removeEventListener("pointermove", onDrag);
    if (!d.moved) {
      if (d.kind === "key") L.send({op: "select", channel: d.tr.name, index: d.i});
      return;
    }
    const m = dragged(d, point(e));
    if (d.kind === "key") {
      L.send({op: "move_key", channel: d.tr.name, index: d.i, t: m.t, value: m.v});
    } else {
      const h = d.k.slice(2, 6);
      if (d.kind === "in") { h[0] = m.dt; h[1] = m.dv; } else { h[2] = m.dt; h[3] = m.dv; }
      L.send({op: "set_handles", channel: d.tr.name, index: d.i, handles: h});
    }
  }

  function keyKeys(e, tr, i, k) {
    const span = (tr.hi - tr.lo) || 1;
    const moves = {ArrowLeft: [-FRAME, 0], ArrowRight: [FRAME, 0], ArrowUp: [0, span / 100], ArrowDown: [0, -span / 100]};
    if (moves[e.key]) {
      const [dt, dv] = moves[e.key];
      L.send({op: "move_key", channel: tr.name, index: i, t: round(Math.max(0, k[0] + dt), 1e6),
              value: round(Math.min(tr.hi, Math.max(tr.lo, k[1] + dv)), 1e6)});
    } else if (e.key === "Delete" || e.key === "Backspace") {
      L.send({op: "delete_key", channel: tr.name, index: i});
    } else if (e.key === "Enter" || e.key === " ") {
      L.send({op: "select", channel: tr.name, index: i});
    } else {
      return;
    }
    e.preventDefault();
  }

  function scrubAt(e) {
    if (e.button !== 0 || !(e.target.getAttribute && e.target.getAttribute("data-scrub"))) return;
    const go = (ev) => {
      const t = Math.min(length(), tOf(point(ev)[0]));
      movePlayhead(t);
      if (playing) { const head = playing.head; stop(); if (!head) play(); } else L.send({op: "scrub", t});
    };
    go(e);
    const move = (ev) => { if (ev.buttons & 1) go(ev); };
    svg.addEventListener("pointermove", move);
    svg.addEventListener("pointerup", () => svg.removeEventListener("pointermove", move), {once: true});
  }

  function status(text) { if (statusText) statusText.textContent = text; }

  // ------------------------------------------------------------------ audio and play
  async function loadAudio(file) {
    actx = actx || new AudioContext();
    let buffer;
    try {
      buffer = await actx.decodeAudioData(await file.arrayBuffer());
    } catch (err) {
      status("Not loaded: " + file.name + " is not audio the browser can decode (" + err + ")");
      return;
    }
    const bins = 1200, data = buffer.getChannelData(0), per = Math.max(1, Math.floor(data.length / bins));
    const peaks = new Float32Array(2 * bins);
    for (let b = 0; b < bins; b++) {
      let lo = 0, hi = 0;
      for (let i = b * per, end = Math.min(data.length, (b + 1) * per); i < end; i++) {
        const s = data[i]; if (s < lo) lo = s; if (s > hi) hi = s;
      }
      peaks[2 * b] = lo; peaks[2 * b + 1] = hi;
    }
    Object.assign(audio, {buffer, name: file.name, peaks});
    status("Audio: " + file.name + ", " + buffer.duration.toFixed(2) + " s");
    L.send({op: "audio", name: file.name, duration: buffer.duration});
    render();
  }

  async function play() {
    if (playing || T.pending) return;
    actx = actx || new AudioContext();
    await actx.resume();
    if (playhead >= Math.max(length(), audio.buffer ? audio.buffer.duration : 0) - 1e-3) movePlayhead(0);
    T.pending = true;
    T.sentAt = performance.now();
    L.send({op: "play", t: playhead, head: !!(headBox && headBox.checked && !headBox.disabled)});
  }

  function start(msg) {
    T.pending = false;
    const lead = actx.outputLatency || actx.baseLatency || 0;  // the sound is heard this long after it is played
    // Timed from the request (sent at once on the click), not from the reply, which may wait behind drawing.
    const due = msg.after_request_s !== undefined ? (T.sentAt + 1000 * msg.after_request_s - performance.now()) / 1000
                                                   : msg.delay_s;
    const delay = Math.max(0, due - lead);
    const when = actx.currentTime + delay;
    if (audio.buffer && msg.t < audio.buffer.duration) {
      source = actx.createBufferSource();
      source.buffer = audio.buffer;
      source.connect(actx.destination);
      source.start(when, msg.t);
    }
    playing = {t0: msg.t, when, head: msg.head};
    T.lastPlay = {t: msg.t, head: msg.head, at: msg.at, audio: !!source,
                  startWall: performance.timeOrigin + performance.now() + (delay + lead) * 1000};
    playButton.textContent = "Pause";
    playButton.setAttribute("aria-label", "Stop timeline");
    requestAnimationFrame(playFrame);
  }

  function playFrame() {
    if (!playing) return;
    const t = playing.t0 + Math.max(0, actx.currentTime - playing.when);
    movePlayhead(t);
    const end = Math.max(length(), audio.buffer ? audio.buffer.duration : 0);
    if (actx.currentTime >= playing.when && performance.now() - lastTick >= 1000 * FRAME) {
      lastTick = performance.now();
      L.send({op: "tick", t: Math.min(t, end)});
    }
    if (t >= end) { stop(); return; }
    requestAnimationFrame(playFrame);
  }

  function stop() {
    if (source) { try { source.stop(); } catch (err) { /* not started */ } source = null; }
    const was = playing;
    playing = null;
    if (playButton) { playButton.textContent = "Play"; playButton.setAttribute("aria-label", "Play timeline"); }
    if (was) L.send({op: "stop"});
  }

  // ------------------------------------------------------------------ the dock
  function build() {
    root = el("div", {id: "likeness-timeline", role: "region", "aria-label": "Timeline"}, document.body, false);
    root.style.cssText = "position:fixed;left:0;bottom:0;height:" + HEIGHT + "px;z-index:5;background:#fff;" +
      "border-top:1px solid #ccd;font:12px system-ui,sans-serif;display:none;flex-direction:column;" +
      "box-shadow:0 -2px 6px rgba(0,0,0,.08)";
    const bar = el("div", {role: "toolbar", "aria-label": "Timeline tools"}, root, false);
    bar.style.cssText = "padding:4px 6px;border-bottom:1px solid #e5e7eb;display:flex;align-items:center";
    playButton = button("Play", () => (playing ? stop() : play()), bar);
    playButton.setAttribute("aria-label", "Play timeline");
    undoButton = button("Undo", () => L.send({op: "undo"}), bar);
    redoButton = button("Redo", () => L.send({op: "redo"}), bar);
    const file = el("input", {type: "file", accept: ".wav,.mp3,audio/wav,audio/mpeg", id: "likeness-audio-file"},
                    bar, false);
    file.style.display = "none";
    const fileLabel = el("label", {for: "likeness-audio-file"}, bar, false);
    fileLabel.textContent = "Load audio";
    fileLabel.style.cssText = "margin-right:8px;padding:2px 9px;border:1px solid #aab;border-radius:3px;cursor:pointer";
    file.addEventListener("change", () => { if (file.files[0]) loadAudio(file.files[0]); });
    const headLabel = el("label", {}, bar, false);
    headBox = el("input", {type: "checkbox"}, headLabel, false);
    headLabel.appendChild(document.createTextNode(" Play on head"));
    headLabel.style.marginRight = "10px";
    timeText = el("span", {}, bar, false);
    timeText.style.cssText = "margin-right:10px;font-variant-numeric:tabular-nums";
    statusText = el("span", {role: "status"}, bar, false);
    statusText.style.color = "#555";
    const scroll = el("div", {}, root, false);
    scroll.style.cssText = "overflow-y:auto;flex:1";
    svg = el("svg", {width: "100%", height: 60, "aria-label": "Tracks"}, scroll);
    svg.style.display = "block";
    svg.addEventListener("pointerdown", scrubAt);
    root.addEventListener("keydown", (e) => {
      if (!(e.ctrlKey || e.metaKey) || e.key.toLowerCase() !== "z" && e.key.toLowerCase() !== "y") return;
      L.send({op: e.shiftKey || e.key.toLowerCase() === "y" ? "redo" : "undo"});
      e.preventDefault();
    });
    setInterval(layout, 250);
    window.addEventListener("resize", () => { layout(); render(); });
  }

  function layout() {
    // Shown while the Animate tab is open, between the page's left edge and the control panel.
    const tab = document.querySelector('[role="tab"][aria-selected="true"]');
    const show = !!tab && tab.textContent.trim() === "Animate";
    const was = root.style.display;
    root.style.display = show ? "flex" : "none";
    const estop = [...document.querySelectorAll("button")].find((b) => b.textContent.trim() === "E-stop");
    const right = estop ? Math.max(0, window.innerWidth - estop.getBoundingClientRect().left + 12) : 0;
    if (root.style.right !== right + "px") { root.style.right = right + "px"; render(); }
    else if (show && was === "none") render();
  }

  L.on("timeline", (msg) => { state = msg; if (!playing && !drag) movePlayhead(msg.playhead); if (!drag) render(); });
  L.on("playhead", (msg) => { if (!playing && !drag) movePlayhead(msg.t); });
  L.on("play", start);
  L.on("refused", (msg) => { T.pending = false; status("Refused: " + msg.error); });
  L.on("error", (msg) => { T.pending = false; status("Error: " + msg.error); });
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", build);
  else build();
})();
