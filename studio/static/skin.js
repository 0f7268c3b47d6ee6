// Likeness Studio: the skin as a three.js mesh the page owns, fed by the studio's own WebSocket.
//
// Runs before viser's client. three.js announces each Scene it makes to a `__THREE_DEVTOOLS__` event target when
// one exists; this script provides one and so sees viser's scene. The server puts a tiny degenerate triangle at
// /skin/anchor (a known point); once it appears, this script hangs its own mesh beside it (same world transform),
// built with the classes of the anchor itself (the client's three.js), and writes every frame from the socket into
// that mesh's position and colour buffers in place, then recomputes the normals and asks the canvas (which draws on
// demand) for a frame. No React re-render, no new geometry.
// The socket also carries JSON messages (the timeline): `Likeness.on(type, fn)` and `Likeness.send(object)`.
(function () {
  "use strict";
  const ANCHOR = [0.123456, -0.654321, 0.0];
  const port = window.LIKENESS_SKIN_PORT;
  const scenes = [];
  const hook = window.__THREE_DEVTOOLS__ || (window.__THREE_DEVTOOLS__ = new EventTarget());
  hook.addEventListener("observe", (e) => { if (e.detail && e.detail.isScene) scenes.push(e.detail); });

  const listeners = {};
  const L = window.Likeness = {
    mesh: null, frames: 0, seq: 0, connected: false,
    on(type, fn) { (listeners[type] = listeners[type] || []).push(fn); },
    send(obj) { if (ws && ws.readyState === 1) { ws.send(JSON.stringify(obj)); return true; } return false; },
  };
  const stamp = (name, detail) => { if (window.__ev) window.__ev.push([name, performance.now(), detail]); };

  // Colours arrive as sRGB bytes; three.js lights and blends in linear space (its colour management).
  const LINEAR = new Float32Array(256);
  for (let i = 0; i < 256; i++) { const c = i / 255; LINEAR[i] = c <= 0.04045 ? c / 12.92 : Math.pow((c + 0.055) / 1.055, 2.4); }

  let pending = null;  // the newest frame not yet written (before the mesh exists, or between animation frames)
  let mesh = null, anchor = null, faces = null;

  function findAnchor() {
    for (const sc of scenes) {
      let hit = null;
      sc.traverse((o) => {
        if (hit || !o.isMesh || !o.geometry || !o.geometry.attributes.position) return;
        const a = o.geometry.attributes.position;
        if (a.count === 3 && Math.abs(a.array[0] - ANCHOR[0]) < 1e-5 && Math.abs(a.array[1] - ANCHOR[1]) < 1e-5) hit = o;
      });
      if (hit) return hit;
    }
    return null;
  }

  function build(nv) {
    const Geometry = anchor.geometry.constructor, Attribute = anchor.geometry.attributes.position.constructor;
    const geometry = new Geometry();
    geometry.setAttribute("position", new Attribute(new Float32Array(nv * 3), 3));
    geometry.setAttribute("color", new Attribute(new Float32Array(nv * 3), 3));
    geometry.setIndex(Array.from(faces));  // three.js picks a 32-bit index buffer for it
    const material = new anchor.material.constructor({vertexColors: true, side: 2, roughness: 0.75, metalness: 0.0});
    mesh = new anchor.constructor(geometry, material);
    mesh.name = "likeness-skin";
    mesh.frustumCulled = false;
    anchor.parent.add(mesh);
    L.mesh = mesh;
  }

  function apply(frame) {
    const {nv, buf} = frame;
    if (!mesh || mesh.geometry.attributes.position.count !== nv) {
      if (mesh) { mesh.parent.remove(mesh); mesh.geometry.dispose(); }
      build(nv);
    }
    const g = mesh.geometry;
    g.attributes.position.array.set(new Float32Array(buf, 16, nv * 3));
    const src = new Uint8Array(buf, 16 + nv * 12, nv * 3), dst = g.attributes.color.array;
    for (let i = 0; i < src.length; i++) dst[i] = LINEAR[src[i]];
    g.attributes.position.needsUpdate = true;
    g.attributes.color.needsUpdate = true;
    g.computeVertexNormals();
    if (!g.boundingSphere) g.computeBoundingSphere();
    // viser's canvas draws on demand (react-three-fiber, frameloop "demand"). Draw the new skin now, as viser does
    // when its canvas resizes, rather than on the renderer's next frame; without the renderer's state, ask for one.
    L.frames++;
    L.seq = frame.seq;
    stamp("skin", frame.seq);
    const root = anchor.__r3f && anchor.__r3f.root, store = root && root.getState ? root.getState() : null;
    if (store && store.gl && store.scene && store.camera) store.gl.render(store.scene, store.camera);
    else if (store && store.invalidate) store.invalidate();
  }

  function tick() {
    if (!anchor && faces) anchor = findAnchor();  // only once the studio sends a mesh (the face view)
    if (anchor && faces && pending) { const f = pending; pending = null; apply(f); }
    requestAnimationFrame(tick);
  }

  let ws = null;
  function connect() {
    if (!port) return;
    ws = new WebSocket("ws://" + (location.hostname || "127.0.0.1") + ":" + port);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { L.connected = true; };
    ws.onclose = () => { L.connected = false; setTimeout(connect, 1000); };
    ws.onmessage = (e) => {
      if (typeof e.data === "string") {
        let msg;
        try { msg = JSON.parse(e.data); } catch (err) { return; }
        (listeners[msg.type] || []).forEach((fn) => fn(msg));
        return;
      }
      const head = new Uint32Array(e.data, 0, 4);
      const [kind, nv, nf, seq] = head;
      stamp("skinrecv", seq);
      if (kind === 1) {
        const off = 16 + nv * 12 + Math.ceil(nv * 3 / 4) * 4;
        faces = new Uint32Array(e.data, off, nf * 3);
        if (mesh) { mesh.parent.remove(mesh); mesh.geometry.dispose(); mesh = null; }
      }
      pending = {nv, seq, buf: e.data};
      // Write it now when the mesh exists: the renderer draws it on its next animation frame.
      if (anchor && faces) { const f = pending; pending = null; apply(f); }
    };
  }
  // Sliders: a value the user gives a slider goes to the studio on this socket at once, ahead of viser's own update
  // (which passes through viser's worker and arrives tens of milliseconds later; the studio then skips it). Only a
  // slider the user is touching counts: the studio moves the others to follow a pose, and those must not echo back.
  let touched = null, touchedUntil = 0;
  const TOUCH_MS = 500;
  function sliderZone(el) {  // the largest element around `el` holding exactly one slider (its row), or null
    let zone = null;
    for (let e = el; e && e !== document.body; e = e.parentElement) {
      const n = e.matches("[role=slider]") ? 1 : e.querySelectorAll("[role=slider]").length;
      if (n > 1) break;
      if (n === 1) zone = e;
    }
    return zone;
  }
  function touch(e) {
    if (e.type === "pointermove" && !e.buttons) return;
    const z = e.target && e.target.nodeType === 1 ? sliderZone(e.target) : null;
    if (z) { touched = z; touchedUntil = performance.now() + TOUCH_MS; }
  }
  for (const t of ["keydown", "pointerdown", "pointermove", "input"]) document.addEventListener(t, touch, {capture: true});
  function sliderName(thumb) {
    const root = thumb.closest("[id]");
    const label = root && document.querySelector(`label[for="${CSS.escape(root.id)}"]`);
    return label ? label.textContent.trim() : thumb.getAttribute("aria-label");
  }
  new MutationObserver((records) => {
    if (!touched || performance.now() > touchedUntil) return;
    for (const r of records) {
      const thumb = r.target;
      if (!touched.contains(thumb)) continue;
      const value = parseFloat(thumb.getAttribute("aria-valuenow"));
      const name = sliderName(thumb);
      if (name && Number.isFinite(value) && L.send({op: "slider", name, value})) stamp("fastsend", name);
    }
  }).observe(document.documentElement, {subtree: true, attributes: true, attributeFilter: ["aria-valuenow"]});

  connect();
  requestAnimationFrame(tick);
})();
