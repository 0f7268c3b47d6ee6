// Likeness Studio: the skin as a three.js mesh the page owns, fed by the studio's own WebSocket.
//
// Runs before viser's client. three.js announces each Scene it makes to a `__THREE_DEVTOOLS__` event target when
// one exists; this script provides one and so sees viser's scene. The server puts a tiny degenerate triangle at
// /skin/anchor (a known point); once it appears, this script hangs its own mesh beside it (same world transform),
// built with the classes of the anchor itself (the client's three.js), and writes every frame from the socket into
// that mesh's position and colour buffers in place, then recomputes the normals and draws the canvas at once. No React
// re-render, no new geometry. The skin is lit per vertex (a small shader: the scene's directional lights and an
// ambient term in the vertex stage, the colour only interpolated per pixel): in a software renderer a physically
// based material with viser's environment map costs several times the rest of the frame per pixel.
// The socket also carries JSON messages (the timeline): `Likeness.on(type, fn)` and `Likeness.send(object)`.
(function () {
  "use strict";
  // A software WebGL renderer (SwiftShader, llvmpipe: no GPU) draws every multisampled pixel on the CPU, which costs
  // more than the rest of a frame: there, WebGL canvases are made without multisampling.
  const getContext = HTMLCanvasElement.prototype.getContext;
  let software = null;
  function isSoftware() {
    if (software !== null) return software;
    software = false;
    try {
      const gl = getContext.call(document.createElement("canvas"), "webgl");
      const info = gl && gl.getExtension("WEBGL_debug_renderer_info");
      const name = gl ? String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER)) : "";
      software = /swiftshader|llvmpipe|softpipe|software/i.test(name);
      const lose = gl && gl.getExtension("WEBGL_lose_context");
      if (lose) lose.loseContext();
    } catch (err) { software = false; }
    return software;
  }
  HTMLCanvasElement.prototype.getContext = function (kind, attrs) {
    if ((kind === "webgl" || kind === "webgl2") && attrs && attrs.antialias && isSoftware()) {
      attrs = Object.assign({}, attrs, {antialias: false});
    }
    return getContext.call(this, kind, attrs);
  };
  // While a skin frame is due (a slider value just went to the studio), the page's other work waits: the main
  // thread must be free to write and draw the skin the moment it arrives, and the renderer free to draw it. A key
  // that moved a pose slider reaches the slider (viser's React re-render, the page's next frame, which a software
  // renderer takes tens of milliseconds to composite) only then, and so do viser's updates from its worker. Both
  // are handed on, in order, once the page's frame with the new skin has begun, or after HOLD_MS at most.
  const HOLD_MS = 120;
  let dueUntil = 0, releaseTimer = 0;
  const held = [];  // viser's messages: [listener, worker, event]
  // Keys held back from a slider: [target, "keydown" | "keyup", KeyboardEvent init]. A key's release waits behind its
  // press, so that listeners that track held keys (viser's keyboard camera) see them in the order they happened.
  const keys = [];
  const replayed = new WeakSet();
  function release() {
    dueUntil = 0;
    clearTimeout(releaseTimer);
    while (keys.length) {
      const [target, type, init] = keys.shift(), e = new KeyboardEvent(type, init);
      replayed.add(e);
      target.dispatchEvent(e);
    }
    while (held.length) { const [fn, self, e] = held.shift(); fn.call(self, e); }
  }
  function hold() {
    dueUntil = performance.now() + HOLD_MS;
    clearTimeout(releaseTimer);
    releaseTimer = setTimeout(release, HOLD_MS);
  }
  function holding(e) {
    if (performance.now() >= dueUntil) { if (held.length || keys.length) release(); return false; }
    return e && e.data && e.data.type === "message_batch";
  }
  const NativeWorker = window.Worker;
  if (NativeWorker) {
    const wrap = (fn) => function (e) {
      if (holding(e) || held.length) {  // in order behind those held
        held.push([fn, this, e]);
        if (!(performance.now() < dueUntil)) release();
      } else fn.call(this, e);
    };
    window.Worker = class extends NativeWorker {
      addEventListener(type, fn, opts) {
        super.addEventListener(type, type === "message" && typeof fn === "function" ? wrap(fn) : fn, opts);
      }
      set onmessage(fn) { super.onmessage = typeof fn === "function" ? wrap(fn) : fn; }
      get onmessage() { return super.onmessage; }
    };
  }
  const ANCHOR = [0.123456, -0.654321, 0.0];
  const port = window.LIKENESS_SKIN_PORT;
  const scenes = [];
  const hook = window.__THREE_DEVTOOLS__ || (window.__THREE_DEVTOOLS__ = new EventTarget());
  hook.addEventListener("observe", (e) => { if (e.detail && e.detail.isScene) scenes.push(e.detail); });

  const listeners = {};
  const L = window.Likeness = {
    mesh: null, frames: 0, seq: 0, connected: false,
    vertexTone: true,  // tone curve and sRGB encoding per vertex where the renderer allows (false: per pixel)
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

  // The skin's material: Lambert lighting evaluated per vertex (front and back faces), then viser's tone mapping and
  // output colour space, so it sits in the scene like its other objects. Light directions and colours are taken
  // from the scene's directional lights before every draw (in view space), ambient light stands in for the
  // environment map. When the canvas is drawn with ACES filmic tone mapping (viser's) or none, into sRGB, the tone
  // curve and the sRGB encoding are applied per vertex as well (TONE_IN_VERTEX: 4 or 0, three.js's constants), so
  // that a pixel only interpolates its colour: in a software renderer the per-pixel curve is a tenth of a frame.
  const VERTEX = `
    uniform vec3 uLightDir[4];
    uniform vec3 uLightColor[4];
    uniform vec3 uAmbient;
    uniform float uExposure;
    varying vec3 vFront;
    varying vec3 vBack;
    #ifdef TONE_IN_VERTEX
    vec3 toneAndEncode(vec3 c) {
      #if TONE_IN_VERTEX == 4
      // ACES filmic as the renderer applies it: exposure, the fitted input transform, the RRT+ODT rational fit, the
      // output transform (matrices column by column).
      c *= uExposure / 0.6;
      c = mat3(0.59719, 0.07600, 0.02840, 0.35458, 0.90834, 0.13383, 0.04823, 0.01566, 0.83777) * c;
      c = (c * (c + 0.0245786) - 0.000090537) / (c * (0.983729 * c + 0.4329510) + 0.238081);
      c = mat3(1.60475, -0.10208, -0.00327, -0.53108, 1.10813, -0.07276, -0.07367, -0.00605, 1.07602) * c;
      #endif
      c = clamp(c, 0.0, 1.0);
      return mix(1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, c * 12.92, vec3(lessThanEqual(c, vec3(0.0031308))));
    }
    #endif
    void main() {
      vec3 n = normalize(normalMatrix * normal);
      vec3 front = uAmbient, back = uAmbient;
      for (int i = 0; i < 4; i++) {
        float d = dot(n, uLightDir[i]);
        front += uLightColor[i] * max(d, 0.0);
        back += uLightColor[i] * max(-d, 0.0);
      }
      vFront = color * front;
      vBack = color * back;
      #ifdef TONE_IN_VERTEX
      vFront = toneAndEncode(vFront);
      vBack = toneAndEncode(vBack);
      #endif
      gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
    }`;
  const FRAGMENT = `
    varying vec3 vFront;
    varying vec3 vBack;
    void main() {
      gl_FragColor = vec4(gl_FrontFacing ? vFront : vBack, 1.0);
      #ifndef TONE_IN_VERTEX
      #include <tonemapping_fragment>
      #include <colorspace_fragment>
      #endif
    }`;

  // Per vertex or per pixel, as the renderer draws this frame (into the canvas or a render target); a change
  // recompiles the material once.
  function toneFor(material, renderer) {
    const tm = renderer.toneMapping;
    const vertex = L.vertexTone && renderer.getRenderTarget() === null && renderer.outputColorSpace === "srgb" && (tm === 4 || tm === 0);
    const want = vertex ? tm : undefined;
    if (material.defines.TONE_IN_VERTEX !== want) {
      if (want === undefined) delete material.defines.TONE_IN_VERTEX;
      else material.defines.TONE_IN_VERTEX = want;
      material.toneMapped = want === undefined;
      material.needsUpdate = true;
    }
    material.uniforms.uExposure.value = renderer.toneMappingExposure;
  }
  // Ambient irradiance (linear) standing in for viser's environment light; lights are divided by pi as three.js's
  // Lambert term does.
  const AMBIENT = 0.4;
  const lightDir = new Float32Array(12), lightColor = new Float32Array(12), ambient = new Float32Array(3);

  function materialClass(type) {  // a material class of the client's three.js, from an object in its scene
    let found = null;
    for (const sc of scenes) {
      sc.traverse((o) => { if (!found && o.material && o.material.type === type) found = o.material.constructor; });
    }
    return found;
  }

  function lightUp(scene, camera) {  // the scene's directional lights in view space, and the ambient term
    const v = camera.matrixWorldInverse.elements;
    let k = 0;
    lightDir.fill(0);
    lightColor.fill(0);
    ambient.fill(AMBIENT);
    scene.traverseVisible((o) => {
      if (o.isAmbientLight || o.isHemisphereLight) {
        ambient[0] += o.color.r * o.intensity; ambient[1] += o.color.g * o.intensity;
        ambient[2] += o.color.b * o.intensity;
      }
      if (!o.isDirectionalLight || k >= 4) return;
      const a = o.matrixWorld.elements, b = o.target.matrixWorld.elements;
      const dx = a[12] - b[12], dy = a[13] - b[13], dz = a[14] - b[14];
      const x = v[0] * dx + v[4] * dy + v[8] * dz, y = v[1] * dx + v[5] * dy + v[9] * dz;
      const z = v[2] * dx + v[6] * dy + v[10] * dz, len = Math.hypot(x, y, z) || 1;
      lightDir[3 * k] = x / len; lightDir[3 * k + 1] = y / len; lightDir[3 * k + 2] = z / len;
      const s = o.intensity / Math.PI;
      lightColor[3 * k] = o.color.r * s; lightColor[3 * k + 1] = o.color.g * s; lightColor[3 * k + 2] = o.color.b * s;
      k++;
    });
  }

  function skinMaterial() {
    const Shader = materialClass("ShaderMaterial");
    if (!Shader) return new anchor.material.constructor({vertexColors: true, side: 2, roughness: 0.75, metalness: 0.0});
    const material = new Shader({
      vertexShader: VERTEX, fragmentShader: FRAGMENT, vertexColors: true, side: 2,
      uniforms: {uLightDir: {value: lightDir}, uLightColor: {value: lightColor}, uAmbient: {value: ambient},
                 uExposure: {value: 1.0}},
      defines: {},
    });
    material.toneMapped = true;
    return material;
  }

  // viser's background-image quad covers the whole canvas and runs its fragment shader on every pixel, discarding
  // each one while no background image is set: in a software renderer that costs about as much as the skin itself.
  // The quad is left out of a frame while its image is off (three.js calls a scene's onBeforeRender before it
  // collects what to draw), and drawn again as soon as the studio sets an image.
  function skipIdleBackground(object) {
    let root = object;
    while (root.parent) root = root.parent;
    const quads = [];
    root.traverse((o) => {
      const u = o.isMesh && o.material && o.material.uniforms;
      if (u && u.enabled && u.colorMap && u.depthMap) quads.push(o);
    });
    if (!quads.length || root.__likenessBackground) return;
    root.__likenessBackground = true;
    const before = root.onBeforeRender;
    root.onBeforeRender = function (...args) {
      for (const q of quads) q.visible = q.material.uniforms.enabled.value === true;
      return before.apply(this, args);
    };
  }

  function build(nv) {
    const Geometry = anchor.geometry.constructor, Attribute = anchor.geometry.attributes.position.constructor;
    const geometry = new Geometry();
    geometry.setAttribute("position", new Attribute(new Float32Array(nv * 3), 3));
    geometry.setAttribute("color", new Attribute(new Float32Array(nv * 3), 3));
    geometry.setAttribute("normal", new Attribute(new Float32Array(nv * 3), 3));
    geometry.setIndex(Array.from(faces));  // three.js picks a 32-bit index buffer for it
    mesh = new anchor.constructor(geometry, skinMaterial());
    mesh.name = "likeness-skin";
    mesh.frustumCulled = false;
    if (mesh.material.isShaderMaterial) {
      mesh.onBeforeRender = (renderer, scene, camera) => {
        lightUp(scene, camera);
        toneFor(mesh.material, renderer);
        mesh.material.uniformsNeedUpdate = true;
      };
    }
    anchor.parent.add(mesh);
    skipIdleBackground(anchor);
    L.mesh = mesh;
  }

  // Vertex normals: the area-weighted sum of the normals of the triangles around each vertex, into the mesh's own
  // buffer (no allocation per frame).
  function computeNormals(g) {
    const p = g.attributes.position.array, n = g.attributes.normal.array, f = faces;
    n.fill(0);
    for (let i = 0; i < f.length; i += 3) {
      const a = 3 * f[i], b = 3 * f[i + 1], c = 3 * f[i + 2];
      const ux = p[b] - p[a], uy = p[b + 1] - p[a + 1], uz = p[b + 2] - p[a + 2];
      const vx = p[c] - p[a], vy = p[c + 1] - p[a + 1], vz = p[c + 2] - p[a + 2];
      const x = uy * vz - uz * vy, y = uz * vx - ux * vz, z = ux * vy - uy * vx;
      n[a] += x; n[a + 1] += y; n[a + 2] += z;
      n[b] += x; n[b + 1] += y; n[b + 2] += z;
      n[c] += x; n[c + 1] += y; n[c + 2] += z;
    }
    for (let i = 0; i < n.length; i += 3) {
      const len = Math.hypot(n[i], n[i + 1], n[i + 2]) || 1;
      n[i] /= len; n[i + 1] /= len; n[i + 2] /= len;
    }
    g.attributes.normal.needsUpdate = true;
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
    computeNormals(g);
    if (!g.boundingSphere) g.computeBoundingSphere();
    // viser's canvas draws on demand (react-three-fiber, frameloop "demand"). Draw the new skin now, as viser does
    // when its canvas resizes, rather than on the renderer's next frame; without the renderer's state, ask for one.
    L.frames++;
    L.seq = frame.seq;
    stamp("skin", frame.seq);
    const root = anchor.__r3f && anchor.__r3f.root, store = root && root.getState ? root.getState() : null;
    if (store && store.gl && store.scene && store.camera) store.gl.render(store.scene, store.camera);
    else if (store && store.invalidate) store.invalidate();
    if (dueUntil) {  // what waited goes on once the page's frame with the new skin has begun (the skin first)
      dueUntil = 0;
      clearTimeout(releaseTimer);
      requestAnimationFrame(() => { releaseTimer = setTimeout(release, 0); });
    }
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
  // Sliders: a value the user gives a pose slider goes to the studio on this socket at once, read from the key or
  // pointer event itself (as the slider will compute it: the studio publishes each pose slider's min, max and step),
  // before viser's React renders the slider and long before viser's own update (which passes through viser's worker
  // and arrives tens of milliseconds later; the studio then skips it). Values that change some other way (a typed
  // number) are sent when the touched slider shows them. Sliders the studio moves to follow a pose never echo back.
  let specs = {};  // name -> [min, max, step] of the pose sliders
  L.on("sliders", (msg) => { specs = msg.sliders || {}; });
  const known = {};  // name -> the value the studio has for that slider from this page, or last showed on it
  const decimals = (step) => { const t = String(step); return t.includes(".") ? t.length - t.indexOf(".") - 1 : 0; };
  const snap = (v, spec) => {  // clamp to the slider's range, rounded to its step's decimals (as the slider does)
    const [min, max, step] = spec;
    return parseFloat(Math.min(Math.max(v, min), max).toFixed(decimals(step)));
  };
  function sendSlider(name, value) {  // true when sent
    if (known[name] === value) return false;
    if (!L.send({op: "slider", name, value})) return false;
    known[name] = value;
    if (faces) hold();  // only a page-owned skin (the face view) gets frames on this socket
    stamp("fastsend", name);
    return true;
  }
  function sliderName(thumb) {
    const root = thumb.closest("[id]");
    const label = root && document.querySelector(`label[for="${CSS.escape(root.id)}"]`);
    return label ? label.textContent.trim() : thumb.getAttribute("aria-label");
  }
  const STEPS = {ArrowRight: 1, ArrowUp: 1, ArrowLeft: -1, ArrowDown: -1};
  const keyInit = (e) => ({key: e.key, code: e.code, keyCode: e.keyCode, which: e.which, shiftKey: e.shiftKey,
                           bubbles: true, cancelable: true, composed: true});
  document.addEventListener("keydown", (e) => {
    if (replayed.has(e)) return;
    const thumb = e.target && e.target.closest ? e.target.closest("[role=slider]") : null;
    if (!thumb || e.altKey || e.ctrlKey || e.metaKey) return;
    const name = sliderName(thumb), spec = specs[name];
    // The slider's value: as shown, or as the keys still held back will leave it.
    const now = keys.length && name in known ? known[name] : parseFloat(thumb.getAttribute("aria-valuenow"));
    if (!spec || !Number.isFinite(now)) return;
    let value;
    if (e.key in STEPS) value = now + STEPS[e.key] * spec[2];
    else if (e.key === "Home") value = spec[0];
    else if (e.key === "End") value = spec[1];
    else return;
    if ((!sendSlider(name, snap(value, spec)) && !keys.length) || !faces) return;
    // The slider itself gets the key once the skin is drawn (in order behind any key still held back).
    e.preventDefault();
    e.stopImmediatePropagation();
    keys.push([thumb, "keydown", keyInit(e)]);
  }, {capture: true});
  document.addEventListener("keyup", (e) => {
    if (replayed.has(e) || !keys.some(([, type, init]) => type === "keydown" && init.code === e.code)) return;
    e.stopImmediatePropagation();
    keys.push([e.target, "keyup", keyInit(e)]);
  }, {capture: true});
  let drag = null;  // the pose slider being dragged: {name, spec, track}
  function pointerValue(e) {
    const r = drag.track.getBoundingClientRect();
    if (!(r.width > 0)) return;
    const [min, max, step] = drag.spec;
    // The slider reads the position from mouse events, whose clientX is a whole pixel.
    const dx = Math.min(Math.max((Math.floor(e.clientX) - r.left) / r.width, 0), 1) * (max - min);
    sendSlider(drag.name, snap((dx !== 0 ? Math.round(dx / step) * step : 0) + min, drag.spec));
  }
  document.addEventListener("pointerdown", (e) => {
    const root = e.button === 0 && e.target && e.target.closest ? e.target.closest(".mantine-Slider-root") : null;
    const thumb = root && root.querySelector("[role=slider]");
    const name = thumb && sliderName(thumb);
    if (!name || !specs[name]) return;
    drag = {name, spec: specs[name], track: root.querySelector(".mantine-Slider-trackContainer") || root};
    pointerValue(e);
  }, {capture: true});
  document.addEventListener("pointermove", (e) => { if (drag && e.buttons & 1) pointerValue(e); }, {capture: true});
  for (const t of ["pointerup", "pointercancel"]) document.addEventListener(t, () => { drag = null; }, {capture: true});

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
  new MutationObserver((records) => {
    const live = touched && performance.now() <= touchedUntil;
    for (const r of records) {
      const thumb = r.target;
      const value = parseFloat(thumb.getAttribute("aria-valuenow"));
      const name = sliderName(thumb);
      if (!name || !Number.isFinite(value)) continue;
      if (live && touched.contains(thumb) && specs[name]) sendSlider(name, value);
      else known[name] = value;  // moved by the studio (or not a pose slider): nothing to send
    }
  }).observe(document.documentElement, {subtree: true, attributes: true, attributeFilter: ["aria-valuenow"]});

  connect();
  requestAnimationFrame(tick);
})();
