"""The learned skin predictor: a KSNN (one tanh hidden layer per axis) in one ONNX graph, run by onnxruntime.

File format (``format_version`` 1), written by ``offline.train.export`` and read here without torch or onnx:

* graph input ``actuators`` float32 (B, A), actuator values in SI (rad, m) in the order of the metadata;
  the graph normalizes them to [0, 1] (``ksnn.lo``, ``ksnn.inv_range``), then for each axis ``k`` in x, y, z
  computes ``tanh(p̂ @ ksnn.k.W1 + ksnn.k.b1) @ ksnn.k.W2 + ksnn.k.b2`` and stacks the three into the output
  ``offsets`` float32 (B, V, 3): surface-vertex offsets from the base mesh, metres.
* ``metadata_props`` (all keys prefixed ``likeness.``): ``format``, ``format_version``, ``head``, ``units``,
  ``actuators`` (JSON list of {name, unit, min, max}, SI), ``hidden``, ``n_vertices``, ``base_vertices``
  (base64 float32 (V, 3)), ``faces`` (base64 int32 (F, 3)), optionally ``face_units`` (JSON names) with
  ``face_unit_offsets`` (base64 float32 (U, V, 3)), and ``training`` (JSON provenance and held-out errors).

Speed: one pose is a row-times-matrix product, bound by streaming the output-layer weights from memory. For float32
files onnxruntime runs without weight prepacking (its packed-GEMM path is 2–3× slower for one row than its
row-times-matrix kernel on the plain layout) and takes the large weights from one NumPy allocation handed over as its
initializers (NumPy asks the kernel for transparent huge pages there, which cuts TLB misses while streaming);
MatMulNBits (int8) keeps its own prepacking. A caller may preallocate the result (``out=``): onnxruntime then writes
straight into it through IOBinding, bound once, so a control loop allocates nothing per call.
"""

from __future__ import annotations

import base64
import json
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import SpecError

FORMAT = "likeness-ksnn"
FORMAT_VERSION = 1
META_PREFIX = "likeness."
INPUT_NAME = "actuators"
OUTPUT_NAME = "offsets"
AXES = ("x", "y", "z")
#: Float initializers at least this large are handed to onnxruntime from one NumPy allocation (module docstring).
_POOL_MIN_BYTES = 1 << 16
#: Alignment of each initializer inside that allocation.
_ALIGN = 64
#: Skin strain range the silicone was validated for (engineering strain of the surface principal stretches).
DEFAULT_STRAIN_RANGE = (-0.20, 0.50)


def encode_array(arr: np.ndarray, dtype: str) -> str:
    """Base64 of the little-endian bytes of ``arr`` cast to ``dtype`` (metadata values must be strings)."""
    return base64.b64encode(np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()).decode()


def decode_array(text: str, dtype: str, shape: tuple[int, ...], source: str, key: str) -> np.ndarray:
    """Inverse of :func:`encode_array`; raises :class:`SpecError` naming ``key`` when the size is wrong."""
    try:
        raw = base64.b64decode(text.encode(), validate=True)
    except ValueError as exc:
        raise SpecError(source, key, f"not valid base64: {exc}") from exc
    arr = np.frombuffer(raw, dtype=np.dtype(dtype).newbyteorder("<"))
    if arr.size != int(np.prod(shape)):
        raise SpecError(source, key, f"holds {arr.size} values, expected shape {shape}")
    return arr.reshape(shape).astype(np.dtype(dtype).newbyteorder("="))


@dataclass(frozen=True)
class KsnnWeights:
    """The weights of the three KSNN heads, axis-major, with inputs in normalized [0, 1] units.

    ``W1`` (3, A, H), ``b1`` (3, H), ``W2`` (3, H, V), ``b2`` (3, V); raw input p maps to p̂ = (p − lo) / (hi − lo).
    """

    lo: np.ndarray
    hi: np.ndarray
    W1: np.ndarray
    b1: np.ndarray
    W2: np.ndarray
    b2: np.ndarray

    @property
    def n_actuators(self) -> int:
        return self.W1.shape[1]

    @property
    def hidden(self) -> int:
        return self.W1.shape[2]

    @property
    def n_vertices(self) -> int:
        return self.W2.shape[2]

    def normalize(self, p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, dtype=np.float64) - self.lo) / (self.hi - self.lo)

    def hidden_activations(self, p: np.ndarray) -> np.ndarray:
        """tanh hidden activations (3, H) for one raw pose (A,)."""
        x = self.normalize(p)
        return np.tanh(np.einsum("a,kah->kh", x, self.W1) + self.b1)

    def offsets(self, p: np.ndarray) -> np.ndarray:
        """Reference NumPy forward pass for one pose: offsets (V, 3) (float64; tests compare ONNX with it)."""
        h = self.hidden_activations(p)
        return (np.einsum("kh,khv->kv", h, self.W2) + self.b2).T


@dataclass(frozen=True)
class ActuatorRange:
    """One model input: actuator name, SI unit and the range the model was trained on."""

    name: str
    unit: str
    min: float
    max: float


class SkinPredictor:
    """Predicts the skin surface from actuator values with a KSNN ONNX model (onnxruntime, torch-free).

    ``predict`` takes one pose (A,) → positions (V, 3) or a batch (B, A) → (B, V, 3); positions are the base
    mesh plus predicted offsets. ``jacobian`` is analytic from the weights; ``principal_stretches`` and
    ``strain_violations`` measure surface stretch per triangle for the skin-strain guard.
    """

    def __init__(self, path: str | Path, threads: int = 1, session: bool = True) -> None:
        """``session=False`` reads the graph's names and metadata from the file itself and leaves onnxruntime (its
        import, about 26 MiB, and the session, about 15 MiB) until the first full pass: for a process that only needs
        the weights and the metadata, as the control loop's (its in-cycle solve and strain guard run on the
        weights). The same checks run either way; only a graph onnxruntime itself refuses shows later."""
        self.path = Path(path)
        source = str(self.path)
        if not self.path.is_file():
            raise SpecError(source, "file", "predictor model not found")
        if threads < 1:
            raise ValueError(f"threads must be at least 1, got {threads!r}")
        self.threads = threads
        self._session_obj: Any = None
        self._session_lock = threading.Lock()
        if session:
            self._open_session()
            inputs = {i.name for i in self._session.get_inputs()}
            outputs = {o.name for o in self._session.get_outputs()}
            meta = dict(self._session.get_modelmeta().custom_metadata_map)
        else:
            from models.onnx_tensors import read_model_info

            names_in, names_out, meta = read_model_info(self.path)
            inputs, outputs = set(names_in), set(names_out)
        if INPUT_NAME not in inputs or OUTPUT_NAME not in outputs:
            raise SpecError(source, "graph", f"needs input {INPUT_NAME!r} and output {OUTPUT_NAME!r}",
                            {"inputs": sorted(inputs), "outputs": sorted(outputs)})
        self.metadata: Mapping[str, str] = meta
        self._parse_metadata(meta, source)
        self._weights: KsnnWeights | None = None
        # One-pose calls reuse one input buffer bound once; a lock keeps concurrent callers off it.
        self._lock = threading.Lock()
        self._x1 = np.zeros((1, self.n_actuators), dtype=np.float32)
        self._io1_obj: Any = None
        self._bound_out = 0
        self._bound_ref: np.ndarray | None = None

    def _open_session(self) -> None:
        """Load the graph into onnxruntime (one thread, prepacking off for float32: see the module docstring)."""
        import onnxruntime as ort

        source = str(self.path)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        from models.onnx_tensors import read_initializers

        try:
            init = read_initializers(self.path)
        except SpecError:
            init = {}  # onnxruntime reports what is wrong with the file
        self._pool: np.ndarray | None = None
        self._pooled: dict[str, Any] = {}
        if not any(name.endswith("_Q8") for name in init):  # float32 (see the module docstring)
            opts.add_session_config_entry("session.disable_prepacking", "1")
            self._pool, self._pooled = _pooled_initializers(init)
            for name, value in self._pooled.items():
                opts.add_initializer(name, value)  # onnxruntime uses this memory: it lives as long as the session
        try:
            self._session_obj = ort.InferenceSession(source, sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types
            raise SpecError(source, "graph", f"onnxruntime cannot load the model: {exc}") from exc

    @property
    def _session(self) -> Any:
        """The onnxruntime session, loaded on first use when the predictor was built without one."""
        if self._session_obj is None:
            with self._session_lock:
                if self._session_obj is None:
                    self._open_session()
        return self._session_obj

    @property
    def _io1(self) -> Any:
        """The one-pose I/O binding over ``_x1`` (made with the session)."""
        if self._io1_obj is None:
            import onnxruntime as ort

            io = self._session.io_binding()
            io.bind_ortvalue_input(INPUT_NAME, ort.OrtValue.ortvalue_from_numpy(self._x1))
            self._io1_obj = io
        return self._io1_obj

    # ------------------------------------------------------------------ metadata
    def _meta(self, meta: Mapping[str, str], key: str, source: str) -> str:
        full = META_PREFIX + key
        if full not in meta:
            raise SpecError(source, f"metadata {full}", "missing")
        return meta[full]

    def _parse_metadata(self, meta: Mapping[str, str], source: str) -> None:
        fmt = self._meta(meta, "format", source)
        if fmt != FORMAT:
            raise SpecError(source, f"metadata {META_PREFIX}format", f"expected {FORMAT!r}", fmt)
        version = self._meta(meta, "format_version", source)
        if version != str(FORMAT_VERSION):
            raise SpecError(source, f"metadata {META_PREFIX}format_version",
                            f"this version reads format {FORMAT_VERSION}", version)
        self.head_name = meta.get(META_PREFIX + "head", "")
        self.units = self._meta(meta, "units", source)
        if self.units != "m":
            raise SpecError(source, f"metadata {META_PREFIX}units", "vertex units must be 'm'", self.units)
        try:
            acts = json.loads(self._meta(meta, "actuators", source))
            self.actuators = tuple(
                ActuatorRange(str(a["name"]), str(a["unit"]), float(a["min"]), float(a["max"])) for a in acts
            )
            self.hidden = int(self._meta(meta, "hidden", source))
            n_vertices = int(self._meta(meta, "n_vertices", source))
            self.training: Mapping[str, Any] = json.loads(meta.get(META_PREFIX + "training", "{}"))
        except (ValueError, KeyError, TypeError) as exc:
            raise SpecError(source, f"metadata {META_PREFIX}actuators/hidden/n_vertices",
                            f"malformed: {exc}") from exc
        if not self.actuators:
            raise SpecError(source, f"metadata {META_PREFIX}actuators", "lists no actuators")
        for a in self.actuators:
            if not a.min < a.max:
                raise SpecError(source, f"metadata {META_PREFIX}actuators ({a.name})", "min must be below max",
                                (a.min, a.max))
        self.base_vertices = decode_array(self._meta(meta, "base_vertices", source), "f4", (n_vertices, 3),
                                          source, META_PREFIX + "base_vertices")
        faces_text = self._meta(meta, "faces", source)
        n_faces = len(base64.b64decode(faces_text)) // 12
        self.faces = decode_array(faces_text, "i4", (n_faces, 3), source, META_PREFIX + "faces").astype(np.int64)
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= n_vertices):
            raise SpecError(source, f"metadata {META_PREFIX}faces", f"indices must lie in [0, {n_vertices})")
        self.face_unit_names: tuple[str, ...] = ()
        self.face_unit_offsets: np.ndarray | None = None
        if META_PREFIX + "face_units" in meta:
            self.face_unit_names = tuple(json.loads(meta[META_PREFIX + "face_units"]))
            self.face_unit_offsets = decode_array(
                self._meta(meta, "face_unit_offsets", source), "f4", (len(self.face_unit_names), n_vertices, 3),
                source, META_PREFIX + "face_unit_offsets")
        self.lo = np.array([a.min for a in self.actuators])
        self.hi = np.array([a.max for a in self.actuators])
        self._base_tri_metric = _triangle_metric(self.base_vertices.astype(np.float64), self.faces)

    @property
    def actuator_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.actuators)

    @property
    def n_actuators(self) -> int:
        return len(self.actuators)

    @property
    def n_vertices(self) -> int:
        return self.base_vertices.shape[0]

    def check_against(self, head: Any, require_full_range: bool = True) -> None:
        """Refuse a head (``models.headspec.HeadSpec``) whose actuators do not match the model, by name.

        The head must list the same actuators in the same order, with the same kind of unit, and every head
        range must lie within the range the model was trained on (no extrapolation at show time). With
        ``require_full_range=False`` a model trained on part of a range is accepted if it covers the head's neutral
        pose; its users must then stay inside :attr:`lo`..:attr:`hi` (the inverse solve clamps to it).
        """
        source = str(self.path)
        model_names = self.actuator_names
        head_names = tuple(a.name for a in head.actuators)
        missing = [n for n in model_names if n not in head_names]
        extra = [n for n in head_names if n not in model_names]
        if missing:
            raise SpecError(source, "actuators", f"model actuator(s) not in head {head.name!r}: {', '.join(missing)}")
        if extra:
            raise SpecError(source, "actuators", f"head {head.name!r} actuator(s) unknown to the model: "
                            f"{', '.join(extra)}")
        if model_names != head_names:
            first = next(i for i, (a, b) in enumerate(zip(model_names, head_names, strict=True)) if a != b)
            raise SpecError(source, "actuators", f"order differs at position {first}: model has "
                            f"{model_names[first]!r}, head has {head_names[first]!r}")
        si_units = {"rotary": "rad", "linear": "m"}
        for ma, ha in zip(self.actuators, head.actuators, strict=True):
            want = si_units.get(getattr(ha, "kind", ""), ha.unit)
            if ma.unit != want:
                raise SpecError(source, f"actuators.{ma.name}.unit", f"model unit differs from head unit {want!r}",
                                ma.unit)
            tol = 1e-9 * max(1.0, abs(ma.max - ma.min))
            if not require_full_range:
                if not ma.min - tol <= ha.neutral <= ma.max + tol:
                    raise SpecError(source, f"actuators.{ma.name}.range",
                                    f"trained range [{ma.min:.6g}, {ma.max:.6g}] {ma.unit} does not cover the head's "
                                    f"neutral {ha.neutral:.6g}")
                continue
            if ha.min < ma.min - tol or ha.max > ma.max + tol:
                raise SpecError(source, f"actuators.{ma.name}.range",
                                f"head range [{ha.min:.6g}, {ha.max:.6g}] {ma.unit} exceeds the trained range "
                                f"[{ma.min:.6g}, {ma.max:.6g}]")

    # ------------------------------------------------------------------ inference
    def _as_batch(self, p: np.ndarray) -> tuple[np.ndarray, bool]:
        arr = np.asarray(p, dtype=np.float32)
        single = arr.ndim == 1
        if single:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != self.n_actuators:
            raise ValueError(f"actuator values must have shape ({self.n_actuators},) or (B, {self.n_actuators}), "
                             f"got {np.shape(p)}")
        if not np.all(np.isfinite(arr)):
            raise ValueError("actuator values must be finite")
        return arr, single

    def _out_array(self, out: np.ndarray | None, batch: int, single: bool) -> np.ndarray:
        shape = (self.n_vertices, 3) if single else (batch, self.n_vertices, 3)
        if out is None:
            return np.empty(shape, dtype=np.float32)
        if (not isinstance(out, np.ndarray) or out.shape != shape or out.dtype != np.float32
                or not out.flags.c_contiguous or not out.flags.writeable):
            raise ValueError(f"out must be a writeable C-contiguous float32 array of shape {shape}, got "
                             f"{getattr(out, 'dtype', type(out).__name__)} {getattr(out, 'shape', '')}")
        return out

    def predict_offsets(self, p: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Offsets from the base mesh: (A,) → (V, 3) or (B, A) → (B, V, 3), float32 metres.

        Returns a new array, or fills ``out`` (float32, C-contiguous, that shape) and returns it: onnxruntime then
        writes straight into it (bound once while the same ``out`` comes back), so a caller that keeps one ``out``
        allocates nothing per call.
        """
        import onnxruntime as ort

        batch, single = self._as_batch(p)
        if out is None:  # onnxruntime's own output allocation (its arena) is cheaper than binding a fresh array
            result = self._session.run([OUTPUT_NAME], {INPUT_NAME: batch})[0]
            return result[0] if single else result
        result = self._out_array(out, len(batch), single)
        shape = [len(batch), self.n_vertices, 3]
        if len(batch) == 1:
            with self._lock:
                self._x1[...] = batch
                if result.ctypes.data != self._bound_out:
                    self._io1.bind_output(OUTPUT_NAME, "cpu", 0, np.float32, shape, result.ctypes.data)
                    self._bound_out = result.ctypes.data
                    self._bound_ref = result  # keep it alive while it is bound
                self._session.run_with_iobinding(self._io1)
            return result
        io = self._session.io_binding()
        io.bind_ortvalue_input(INPUT_NAME, ort.OrtValue.ortvalue_from_numpy(batch))
        io.bind_output(OUTPUT_NAME, "cpu", 0, np.float32, shape, result.ctypes.data)
        self._session.run_with_iobinding(io)
        return result

    def predict(self, p: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Surface vertex positions (base + offsets): (A,) → (V, 3) or (B, A) → (B, V, 3), float32 metres.

        ``out`` as in :meth:`predict_offsets`.
        """
        result = self.predict_offsets(p, out)
        result += self.base_vertices
        return result

    # ------------------------------------------------------------------ weights and Jacobian
    @property
    def weights(self) -> KsnnWeights:
        """The KSNN weights read from the graph initializers (dequantized for the int8 variant)."""
        if self._weights is None:
            self._weights = load_weights(self.path, self.hidden, self.n_vertices, self.n_actuators)
        return self._weights

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        """Analytic d(positions)/d(actuators) at one raw pose: (V*3, A), rows ordered vertex-major (v*3 + axis)."""
        w = self.weights
        p = np.asarray(p, dtype=np.float64)
        if p.shape != (self.n_actuators,):
            raise ValueError(f"jacobian takes one pose of shape ({self.n_actuators},), got {p.shape}")
        h = w.hidden_activations(p)  # (3, H)
        dh = (1.0 - h * h)[:, None, :] * w.W1 / (w.hi - w.lo)[None, :, None]  # (3, A, H)
        jac = np.einsum("kah,khv->vka", dh, w.W2)  # (V, 3, A)
        return jac.reshape(self.n_vertices * 3, self.n_actuators)

    # ------------------------------------------------------------------ surface stretch
    def principal_stretches(self, positions: np.ndarray) -> np.ndarray:
        """Principal in-plane stretches (min, max) of every surface triangle vs the base mesh: (T, 2) or (B, T, 2)."""
        g = _triangle_metric(np.asarray(positions), self.faces).astype(np.float64)
        return _stretches(self._base_tri_metric, g)

    def strain_extremes(self, positions: np.ndarray) -> tuple[float, float]:
        """Smallest and largest principal engineering strain over all surface triangles of one pose."""
        s = self.principal_stretches(positions)
        return float(s[..., 0].min() - 1.0), float(s[..., 1].max() - 1.0)

    def strain_violations(self, positions: np.ndarray,
                          strain_range: tuple[float, float] = DEFAULT_STRAIN_RANGE) -> np.ndarray:
        """Indices of triangles whose principal strains leave ``strain_range`` (one pose)."""
        s = self.principal_stretches(positions)
        lo, hi = strain_range
        return np.flatnonzero((s[:, 0] - 1.0 < lo) | (s[:, 1] - 1.0 > hi))


def load_weights(path: str | Path, hidden: int, n_vertices: int, n_actuators: int) -> KsnnWeights:
    """Read the KSNN weights of a predictor file from its initializers (float or MatMulNBits int8)."""
    from models.onnx_tensors import read_initializers

    source = str(path)
    init = read_initializers(path)

    def get(name: str, shape: tuple[int, ...]) -> np.ndarray:
        arr = init[name].astype(np.float64) if name in init else _dequantize_nbits(init, name, shape, source)
        if arr.shape != shape:
            raise SpecError(source, f"initializer {name}", f"expected shape {shape}", arr.shape)
        return arr

    lo = get("ksnn.lo", (n_actuators,))
    inv = get("ksnn.inv_range", (n_actuators,))
    hi = lo + 1.0 / inv
    W1 = np.stack([get(f"ksnn.{k}.W1", (n_actuators, hidden)) for k in AXES])
    b1 = np.stack([get(f"ksnn.{k}.b1", (hidden,)) for k in AXES])
    W2 = np.stack([get(f"ksnn.{k}.W2", (hidden, n_vertices)) for k in AXES])
    b2 = np.stack([get(f"ksnn.{k}.b2", (n_vertices,)) for k in AXES])
    return KsnnWeights(lo, hi, W1, b1, W2, b2)


def _dequantize_nbits(init: Mapping[str, np.ndarray], name: str, shape: tuple[int, ...], source: str) -> np.ndarray:
    """Rebuild a float (K, N) MatMul weight from onnxruntime's MatMulNBits 8-bit blocks (symmetric, zp 128)."""
    q = init.get(name + "_Q8")
    scales = init.get(name + "_scales")
    if q is None or scales is None or len(shape) != 2:
        raise SpecError(source, f"initializer {name}", "missing (neither float nor 8-bit MatMulNBits weights)")
    k, n = shape
    zp = init.get(name + "_zero_points")
    n_blocks = q.shape[1]
    block = q.shape[2]
    vals = q.reshape(n, n_blocks * block).astype(np.float64)
    zero = np.repeat(zp.reshape(n, -1)[:, :n_blocks].astype(np.float64), block, axis=1) if zp is not None else 128.0
    sc = np.repeat(scales.reshape(n, n_blocks).astype(np.float64), block, axis=1)
    return ((vals - zero) * sc)[:, :k].T.copy()


def surface_principal_stretches(base: np.ndarray, faces: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Principal in-plane stretches (min, max) of each triangle of ``positions`` (..., V, 3) against ``base``."""
    return _stretches(_triangle_metric(np.asarray(base, dtype=np.float64), faces),
                      _triangle_metric(np.asarray(positions, dtype=np.float64), faces))


def _pooled_initializers(init: Mapping[str, np.ndarray]) -> tuple[np.ndarray | None, dict[str, Any]]:
    """The large initializers copied into one NumPy allocation, as onnxruntime values over that memory.

    NumPy backs allocations of 4 MiB and more with transparent huge pages where the kernel allows it, which
    onnxruntime's own copies do not get; streaming the output-layer weights then takes fewer TLB misses. Returns the
    pool (the caller keeps it alive as long as the session) and {name: OrtValue}.
    """
    import onnxruntime as ort

    big = {n: a for n, a in init.items() if a.nbytes >= _POOL_MIN_BYTES}
    if not big:
        return None, {}
    offsets, total = {}, 0
    for name, arr in big.items():
        offsets[name] = total
        total += -(-arr.nbytes // _ALIGN) * _ALIGN
    pool = np.empty(total + _ALIGN, dtype=np.uint8)
    start = -pool.ctypes.data % _ALIGN
    values = {}
    for name, arr in big.items():
        o = start + offsets[name]
        view = pool[o:o + arr.nbytes].view(arr.dtype).reshape(arr.shape)
        view[...] = arr
        values[name] = ort.OrtValue.ortvalue_from_numpy(view)
    return pool, values


def _triangle_metric(pos: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """First fundamental form of each triangle in its edge basis: (..., T, 3) entries (e1·e1, e1·e2, e2·e2)."""
    tri = np.take(pos, faces, axis=-2)  # (..., T, 3 corners, 3)
    e1 = tri[..., 1, :] - tri[..., 0, :]
    e2 = tri[..., 2, :] - tri[..., 0, :]
    return np.stack([np.einsum("...i,...i->...", e1, e1), np.einsum("...i,...i->...", e1, e2),
                     np.einsum("...i,...i->...", e2, e2)], axis=-1)


def _stretches(g0: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Principal stretches from base and deformed metrics: sqrt of the eigenvalues of G0⁻¹ G (2x2, closed form)."""
    a0, b0, c0 = g0[..., 0], g0[..., 1], g0[..., 2]
    a, b, c = g[..., 0], g[..., 1], g[..., 2]
    det0 = a0 * c0 - b0 * b0
    det0 = np.where(det0 > 0, det0, np.nan)  # degenerate base triangles give NaN, never a false pass
    tr = (c0 * a - 2.0 * b0 * b + a0 * c) / det0  # trace of G0⁻¹ G
    det = (a * c - b * b) / det0
    disc = np.sqrt(np.maximum(tr * tr / 4.0 - det, 0.0))
    lam_max = tr / 2.0 + disc
    lam_min = np.maximum(tr / 2.0 - disc, 0.0)
    return np.stack([np.sqrt(lam_min), np.sqrt(lam_max)], axis=-1)


def actuator_metadata(names: Sequence[str], units: Sequence[str], lo: np.ndarray, hi: np.ndarray) -> str:
    """The JSON text of the ``actuators`` metadata entry."""
    return json.dumps([{"name": n, "unit": u, "min": float(a), "max": float(b)}
                       for n, u, a, b in zip(names, units, lo, hi, strict=True)])
