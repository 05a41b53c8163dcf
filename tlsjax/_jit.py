"""How tlsjax compiles: ``jax.jit`` with the XLA options chosen for this engine, in one place.

XLA's CPU backend has two code generators for fused kernels: the newer MLIR "fusion emitters"
(the default in current jaxlib) and the older LLVM IR emitters. For tlsjax's programs the older
ones compile about twice as fast and without the compiler's memory transient of about 0.5 GB,
while the compiled adjustment runs at the same speed for large networks, planes and Monte Carlo
and 7 % (4 APs) to 20 % (23 APs) slower for the small Chow room (measured 2026-11-24 in one
process, both executables timed alternately; ``benchmarks/README.md``). A self-calibration is
compiled once and run a few times (a CLI call, a notebook cell), so the compile is most of what
a user waits for, and the memory transient set the peak of a plane adjustment: the older
emitters are chosen.

The option is a field of XLA's debug options; a jaxlib without it rejects it when compiling, so
it is tried once, on a trivial function, at the first compile (not at import: the backend must
not start before the user's own XLA settings, e.g. the host device count, are read).

**The persistent compilation cache.** A calibration compiles a few programs for seconds; run
again on a network of the same shape (the CLI on the next data set, a notebook restarted) it
should compile nothing. JAX's persistent cache stores an executable under a hash of its
program, the compile options, the backend and the versions of jax and jaxlib; tlsjax turns it
on at import (:func:`use_persistent_cache`) in a folder of its own version,
``$TLSJAX_CACHE_DIR/tlsjax-<version>`` (default ``~/.cache/tlsjax/jax``; ``off`` turns it
off), for every program, small ones included (JAX's default stores only those that took over a
second to compile). It is bounded (:data:`CACHE_MAX_BYTES`, least recently used evicted;
``$TLSJAX_CACHE_MAX_BYTES`` changes the bound or removes it) and safe under concurrent
processes: reads and writes take a file lock (``filelock``). A user who
set ``jax_compilation_cache_dir`` themselves keeps their cache and its settings.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ._version import __version__

#: XLA options of every compiled tlsjax function (where this jaxlib knows them). The second
#: keeps YNNPACK (XLA's CPU library kernels) to single matrix products: its fused reductions
#: and elementwise subgraphs ran 2-5x slower than XLA's own loops at tlsjax's shapes (a sum
#: over 120 targets of per-cell products: 13-22 against 3-5 us; the Chow room's assembly 385
#: against 185 us, measured 2026-11-27 on one core, alternately).
PREFERRED_OPTIONS = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT",
}


#: XLA flags for processes that compile much and compute little (the test suite, the
#: notebooks' test kernels, the documentation's examples): no backend (LLVM) optimisation, which
#: changes results only by rounding, and for programs that tlsjax does not compile itself (a
#: test's own ``jax.jit`` around ``grad`` or ``vmap``) the code generators of its own programs.
QUICK_COMPILE_FLAGS = {
    "xla_backend_optimization_level": "0",
    "xla_cpu_use_fusion_emitters": str(PREFERRED_OPTIONS["xla_cpu_use_fusion_emitters"]).lower(),
}


def quick_compile_flags(flags: str = "") -> str:
    """``flags`` (a value of ``XLA_FLAGS``) with each of :data:`QUICK_COMPILE_FLAGS` it does not
    name added; set it before JAX starts its backend."""
    for name, value in QUICK_COMPILE_FLAGS.items():
        if name not in flags:
            flags = f"{flags} --{name}={value}"
    return flags.strip()


@functools.cache
def compiler_options(quick: bool = False) -> dict:
    """The options of :data:`PREFERRED_OPTIONS` (and of :data:`QUICK_OPTIONS` when ``quick``)
    this jaxlib accepts: all of them in one trial compile, each alone only if that fails."""
    wanted = dict(PREFERRED_OPTIONS, **(QUICK_OPTIONS if quick else {}))

    def accepted(options) -> bool:
        try:
            jax.jit(lambda x: x + 1.0).lower(jnp.zeros(())).compile(compiler_options=options)
        except Exception:  # an older or newer jaxlib without an option: its default
            return False
        return True

    if accepted(wanted):
        return wanted
    return {k: v for k, v in wanted.items() if accepted({k: v})}


#: Options of a program that compiles much and runs little (:class:`StoredProgram` ``quick``):
#: no backend (LLVM) optimisation, which changes results only by rounding. The score tests'
#: program, run twice per calibration, compiles beside the adjustment's on a first run: the two
#: share the two cores, and this one's LLVM time at full optimisation took a third of the
#: adjustment's compile (``tlsjax calibrate`` of the demo room: first run 5.2 -> 4.6 s; each of its
#: two calls 5 ms slower, 8 -> 13 ms).
QUICK_OPTIONS = {"xla_backend_optimization_level": 0}


class _Jit:
    """``jax.jit(fun, **kwargs)`` with :func:`compiler_options`, made at the first use."""

    def __init__(self, fun, kwargs):
        functools.update_wrapper(self, fun)
        self._fun, self._kwargs = fun, kwargs

    @functools.cached_property
    def _jitted(self):
        return jax.jit(self._fun, compiler_options=compiler_options(), **self._kwargs)

    @functools.cached_property
    def _nested(self):
        return jax.jit(self._fun, **self._kwargs)

    def __call__(self, *args, **kwargs):
        # Compiler options belong to a top-level compile: inside a caller's jit, grad, jvp or
        # vmap this is a nested jit, compiled (and optimised) with the caller's program.
        if not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((args, kwargs))):
            try:
                return self._jitted(*args, **kwargs)
            except ValueError as exc:  # inside a trace with concrete arguments only
                if "compiler_options" not in str(exc):
                    raise
        return self._nested(*args, **kwargs)

    def __getattr__(self, name):  # lower, trace, eval_shape, _cache_size, ...
        if name.startswith("__") or name in ("_fun", "_kwargs", "_jitted", "_nested"):
            raise AttributeError(name)
        return getattr(self._jitted, name)


def jit(fun=None, **kwargs):
    """``jax.jit`` with tlsjax's compiler options; usable as ``@jit`` or
    ``@functools.partial(jit, static_argnums=...)``."""
    if fun is None:
        return functools.partial(jit, **kwargs)
    return _Jit(fun, kwargs)


#: Environment variable naming the folder of the persistent compilation cache ("off": none).
CACHE_ENV = "TLSJAX_CACHE_DIR"
#: Its size bound: least recently used entries are evicted beyond it (an adjustment's
#: executable is about 1 MB).
CACHE_MAX_BYTES = 1 << 30
#: Environment variable overriding :data:`CACHE_MAX_BYTES` (bytes; "unbounded" or a number
#: <= 0: no bound). JAX's bounded cache scans every entry of the folder on each store (its
#: eviction heap), 12 ms at 1,000 entries and 43 ms at 3,000 (measured here): a throw-away
#: folder that takes thousands of programs, as the test suite's, is better unbounded.
CACHE_MAX_BYTES_ENV = "TLSJAX_CACHE_MAX_BYTES"


def cache_max_bytes() -> int:
    """The cache's bound in bytes (``$TLSJAX_CACHE_MAX_BYTES``), -1 for none. A value that is
    not a number warns and keeps the default (read at import: no traceback for a typo)."""
    raw = os.environ.get(CACHE_MAX_BYTES_ENV, "").strip().lower()
    if not raw:
        return CACHE_MAX_BYTES
    if raw in ("unbounded", "none", "off"):
        return -1
    try:
        n = int(float(raw))
    except ValueError:
        warnings.warn(
            f"{CACHE_MAX_BYTES_ENV}={raw!r} is not a number of bytes or 'unbounded': the "
            f"compilation cache keeps its default bound of {CACHE_MAX_BYTES} bytes",
            stacklevel=2,
        )
        return CACHE_MAX_BYTES
    return n if n > 0 else -1


_OFF = ("", "0", "off", "none", "false", "no")


def cache_dir() -> str | None:
    """The folder of tlsjax's compiled programs (:envvar:`TLSJAX_CACHE_DIR`, default
    ``~/.cache/tlsjax/jax``, one subfolder per tlsjax version), or None when turned off."""
    base = os.environ.get(CACHE_ENV)
    if base is None:
        home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        base = os.path.join(home, "tlsjax", "jax")
    if base.strip().lower() in _OFF:
        return None
    return os.path.join(base, f"tlsjax-{__version__}")


def use_persistent_cache() -> str | None:
    """Turn on JAX's persistent compilation cache in :func:`cache_dir` for every program of
    this process (module docstring); the folder in use, or None. Leaves a cache the user set
    up (``jax_compilation_cache_dir``) as it is; turns nothing on where the folder cannot be
    made. Process-wide, as JAX's cache is: the user's own programs are cached there too."""
    own = jax.config.jax_compilation_cache_dir
    if own:
        return own
    path = cache_dir()
    if path is None:
        return None
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    bound = cache_max_bytes()
    try:
        import filelock  # JAX locks the folder with it when the size is bounded
    except ImportError:  # unbounded and unlocked: still correct (a torn read recompiles)
        bound = -1
    jax.config.update("jax_compilation_cache_max_size", bound)
    if bound > 0:
        _repair_cache(path, filelock)
    # JAX decides at its first compile whether this process uses the cache; a program compiled
    # before this call (the user's own) made it decide without one: let it decide again.
    from jax.experimental.compilation_cache import compilation_cache

    compilation_cache.reset_cache()
    return path


def _repair_cache(path: str, filelock) -> None:
    """Give every entry of JAX's size-bounded cache its access-time file.

    JAX writes an entry, then its ``<key>-atime`` file; a process killed between the two (Ctrl-C
    during a compile) leaves an entry without one, and from then on every store in the folder
    fails in JAX's eviction scan (a warning per program, nothing cached). Written here, under
    JAX's own lock, with the oldest possible time, so the orphan is the first evicted."""
    try:
        names = set(os.listdir(path))
        orphans = [n[: -len("-cache")] for n in names if n.endswith("-cache")]
        orphans = [k for k in orphans if k + "-atime" not in names]
        if not orphans:
            return
        with filelock.FileLock(os.path.join(path, ".lockfile"), timeout=10):
            for key in orphans:
                atime = os.path.join(path, key + "-atime")
                if os.path.exists(os.path.join(path, key + "-cache")) and not os.path.exists(atime):
                    with open(atime, "wb") as f:
                        f.write((0).to_bytes(8, "little"))
    except (OSError, filelock.Timeout):  # a cache that cannot be repaired only costs compiles
        pass


# --- Programs stored traced (jax.export) ----------------------------------------------------
# The persistent cache skips XLA's compile, not the tracing and lowering of tlsjax's Python
# (seconds for the adjustment). A program whose key holds everything it depends on is stored
# traced and lowered, as a serialized ``jax.export.Exported`` beside the cache; a later process
# with the same key loads it and compiles it (from the persistent cache): no tracing.


def _stable(obj):
    """A description of ``obj`` that is equal across processes when ``obj`` is (dataclasses
    field by field, with their types; tlsjax's own functions by name, their code being in
    :func:`_code_digest`); raises TypeError for what has none (e.g. a user's function)."""
    if obj is None or isinstance(obj, (bool, int, float, str, bytes)):
        return repr(obj)
    if isinstance(obj, (tuple, list)):
        return "(" + ",".join(_stable(o) for o in obj) + ")"
    if isinstance(obj, dict):
        return "{" + ",".join(f"{_stable(k)}:{_stable(v)}" for k, v in sorted(obj.items())) + "}"
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        fields = ",".join(
            f"{f.name}={_stable(getattr(obj, f.name))}" for f in dataclasses.fields(obj)
        )
        return f"{type(obj).__module__}.{type(obj).__qualname__}({fields})"
    if isinstance(obj, jax.tree_util.PyTreeDef):
        return repr(obj)
    if callable(obj) and getattr(obj, "__module__", "").startswith("tlsjax."):
        return f"{obj.__module__}.{obj.__qualname__}"  # tlsjax's code: in the source digest
    raise TypeError(f"no stable description of {type(obj).__name__}")


@functools.cache
def _code_digest() -> str:
    """Versions of tlsjax and of what its programs are traced with, and a hash of tlsjax's own
    source (a development install keeps its version number while the code changes)."""
    import hashlib
    import importlib.metadata as md
    from pathlib import Path

    h = hashlib.sha256()
    for pkg in ("jax", "jaxlib", "numpy"):
        try:
            h.update(f"{pkg}={md.version(pkg)};".encode())
        except md.PackageNotFoundError:
            h.update(f"{pkg}=?;".encode())
    h.update(__version__.encode())
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def traced_folder() -> str | None:
    """Where :class:`StoredProgram` keeps its programs: ``traced/`` in the compilation cache
    folder in use (a local one), or None."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder or "://" in folder:
        return None
    return os.path.join(folder, "traced")


#: Programs :meth:`StoredProgram.prepare` queued: (program, leaves, avals), started in the
#: background at the next compile of another stored program.
_QUEUED: list = []


class Background:
    """``fun()`` computed in a thread of its own, e.g. a compile (XLA compiles without
    Python's lock); :meth:`result` waits for it and returns its value or raises its error.
    Not a daemon thread: an interpreter that exits waits for the work to end rather than tear
    down under it."""

    def __init__(self, fun):
        self._out = None
        self._thread = threading.Thread(target=self._run, args=(fun,))
        self._thread.start()

    def _run(self, fun):
        try:
            self._out = (fun(), None)
        except BaseException as err:  # noqa: BLE001 - raised where the result is asked for
            self._out = (None, err)

    def result(self):
        self._thread.join()
        value, err = self._out
        if err is not None:
            raise err
        return value


class StoredProgram:
    """``jax.jit(fun)`` of flat array arguments, stored traced in the cache folder (above) under
    ``key``, a description of everything ``fun`` closes over; without a cache folder, or for a
    key without a stable description (e.g. a user's own AP term, a function), a plain
    ``jit``.

    ``host=True``: a call returns its outputs on the host, as numpy arrays in the output's
    pytree, fetched in one transfer per dtype: the program concatenates its outputs into one
    buffer per dtype and the host splits them into views (one transfer costs 7-10 us per array
    of a few dozen; the adjustment's result has about forty). ``quick=True``: compiled with
    :data:`QUICK_OPTIONS`, for a program that compiles much and runs little."""

    def __init__(self, fun, key, host: bool = False, quick: bool = False):
        self._fun, self._key, self._host = fun, key, host
        self._quick = quick
        self._calls = {}  # avals -> (compiled callable of flat leaves, output treedef, layout)
        self._last = ((), None)  # the last call's jax-array arguments and its entry
        self._pending = {}  # avals -> :class:`Background` preparing it, None: queued
        self._lock = threading.Lock()

    def prepare(self, *leaves) -> None:
        """Have the program for arguments shaped as ``leaves`` traced (or loaded) and compiled
        in a background thread, unless it is at hand or under way, starting when the calling
        thread next compiles another stored program: XLA compiles without Python's lock, so
        the second program's trace runs beside the first one's compile (both traces at once
        would only take turns), and its compile beside the Python work that follows. A later
        call with such arguments waits for it instead of compiling; one that comes before any
        other compile does the work itself. Nothing is dispatched when the entry exists."""
        avals = tuple(_aval(x) for x in leaves)
        with self._lock:
            if avals in self._calls or avals in self._pending:
                return
            self._pending[avals] = None  # queued: no thread yet
        _QUEUED.append((self, leaves, avals))

    def _start(self, leaves, avals):
        with self._lock:
            self._pending[avals] = Background(lambda: self._prepare(leaves, avals))

    def _prepare(self, leaves, avals):
        try:
            entry = self._load_or_trace(leaves, avals)
            entry[0].lower(*leaves).compile()  # the compiled call, stored with the jit
        except Exception:  # noqa: BLE001 - the call that needs it traces and reports it
            entry = None
        with self._lock:
            if entry is not None:
                self._calls.setdefault(avals, entry)
            del self._pending[avals]

    def _entry(self, leaves, avals):
        """The entry for ``avals``: at hand, prepared in the background (waited for), or
        loaded or traced here."""
        with self._lock:
            task = self._pending.get(avals)
            if avals in self._pending and task is None:  # queued, not started: done here
                del self._pending[avals]
                _QUEUED[:] = [q for q in _QUEUED if not (q[0] is self and q[2] == avals)]
        if task is not None:
            task.result()  # :meth:`_prepare` reports no error: on one, the entry is traced here
        call = self._calls.get(avals)
        if call is None:
            call = self._calls[avals] = self._load_or_trace(leaves, avals)
        return call

    def __call__(self, *leaves):
        last, call = self._last
        # The same (immutable) jax arrays as the last call, e.g. an analysed adjustment solved
        # again: its entry without the abstract values (about 2 us per argument).
        if not (
            call is not None
            and len(last) == len(leaves)
            and all(a is b for a, b in zip(last, leaves))
        ):
            # Per call only the arguments' abstract values (cheap: jax arrays carry theirs);
            # the stable description (shape, dtype, weak type) on a miss.
            seen = tuple(x.aval if hasattr(x, "aval") else _aval(x) for x in leaves)
            call = self._calls.get(seen)
            if call is None:
                call = self._entry(leaves, tuple(_aval(x) for x in leaves))
                self._calls[seen] = call
                # This call compiles (or loads) now: the programs queued by :meth:`prepare`
                # start beside it.
                while _QUEUED:
                    program, queued_leaves, queued_avals = _QUEUED.pop(0)
                    program._start(queued_leaves, queued_avals)
            if all(isinstance(x, jax.Array) for x in leaves):
                self._last = (leaves, call)
        fn, treedef, layout = call
        out = fn(*leaves)
        if layout is not None:
            out = _unpack(jax.device_get(out), layout)
        return out if treedef is None else jax.tree.unflatten(treedef, out)

    def _file(self, avals):
        folder = traced_folder()
        if folder is None:
            return None
        try:
            desc = _stable(
                (self._key, self._host, avals, sorted(compiler_options(self._quick).items()))
            )
        except TypeError:
            return None
        import hashlib

        digest = hashlib.sha256((_code_digest() + desc).encode()).hexdigest()
        return os.path.join(folder, f"{digest}.bin")

    def _flat(self, record: dict):
        """``fun`` with flat outputs (packed when ``host``); ``record`` gets the output's
        treedef and the packing layout at the trace."""

        def flat(*args):
            leaves_out, record["tree"] = jax.tree.flatten(self._fun(*args))
            if not self._host:
                return leaves_out
            packed, record["layout"] = _pack(leaves_out)
            return packed

        return flat

    def _load_or_trace(self, leaves, avals):
        path = self._file(avals)
        if path is None:
            return self._plain(leaves)
        import pickle

        from jax import export

        try:
            with open(path, "rb") as f:
                blob, skeleton, layout = pickle.load(f)
            exported = export.deserialize(blob)
            treedef = jax.tree.structure(pickle.loads(skeleton))
            os.utime(path)  # recently used: the folder is pruned by modification time
        except Exception:  # none yet (or unreadable): trace, export and store
            record = {}
            try:
                exported = export.export(jax.jit(self._flat(record)))(*leaves)
                treedef, layout = record["tree"], record.get("layout")
                skeleton = jax.tree.unflatten(treedef, list(range(treedef.num_leaves)))
                data = pickle.dumps((exported.serialize(), pickle.dumps(skeleton), layout))
            except Exception:  # not exportable here (e.g. no flatbuffers): as before
                return self._plain(leaves)
            _write_atomically(path, data)
        call = functools.wraps(self._fun)(lambda *args: exported.call(*args))
        return jax.jit(call, compiler_options=compiler_options(self._quick)), treedef, layout

    def _plain(self, leaves):
        """A plain ``jit`` (not stored); traced here once for its output's structure."""
        if not self._host:
            return jax.jit(self._fun, compiler_options=compiler_options(self._quick)), None, None
        record = {}
        fn = jax.jit(
            functools.wraps(self._fun)(self._flat(record)),
            compiler_options=compiler_options(self._quick),
        )
        fn.lower(*leaves)  # the trace fills ``record`` (reused by the first call)
        return fn, record["tree"], record["layout"]


def _pack(leaves):
    """Outputs concatenated into one flat buffer per dtype; returns (buffers, layout) with
    layout = per leaf (buffer index, offset, shape) and the buffers' dtypes."""
    import jax.numpy as jnp

    groups: dict = {}
    layout = []
    for x in leaves:
        dt = str(x.dtype)
        parts = groups.setdefault(dt, [])
        offset = sum(int(np.prod(p.shape)) for p in parts)
        layout.append((dt, offset, tuple(x.shape)))
        parts.append(x)
    names = sorted(groups)
    buffers = tuple(jnp.concatenate([p.reshape(-1) for p in groups[n]]) for n in names)
    index = {n: i for i, n in enumerate(names)}
    return buffers, tuple((index[dt], off, shape) for dt, off, shape in layout)


def _unpack(buffers, layout) -> list:
    """Numpy views of the packed outputs (:func:`_pack`) on the host."""
    # math.prod, not np.prod: about 40 outputs a call, and np.prod of a tuple costs 3 us.
    return [buffers[b][off : off + math.prod(shape)].reshape(shape) for b, off, shape in layout]


def _aval(x) -> tuple:
    """Shape, dtype and weak type of an argument (what a compiled program is specialised on)."""
    if not hasattr(x, "dtype"):
        x = np.asarray(x)
    return tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False))


#: Traced programs kept in the cache folder; the least recently used beyond it are removed
#: (a program of an older tlsjax source is never read again).
MAX_TRACED = 256


def _write_atomically(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file renamed into place (a concurrent
    reader sees the whole file or none), and keep the folder to :data:`MAX_TRACED` files."""
    import tempfile

    folder = os.path.dirname(path)
    try:
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
        files = [e for e in os.scandir(folder) if e.name.endswith(".bin")]
        if len(files) > MAX_TRACED:
            files.sort(key=lambda e: e.stat().st_mtime)
            for e in files[: len(files) - MAX_TRACED]:
                os.remove(e.path)
    except OSError:  # a full disk, a concurrent removal: the program is traced next time
        pass


use_persistent_cache()
