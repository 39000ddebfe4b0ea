"""Traced programs kept across runs: the part of a warm start that the compilation cache
cannot skip.

JAX's persistent cache (`_cache.enable_compilation_cache`) keeps compiled XLA programs,
keyed by the program; to find one, a run must still trace its Python function to that
program and lower it, about a second for a fit's solve of a six-node model with a
nonlinear effect, paid for every model structure an investigation tries. `stored_jit`
keeps the traced program itself (`jax.export`: serialized StableHLO) in a `traced/`
folder of the compilation cache, so that a warm run only loads it.

An entry's key is everything the trace depends on: the function's name, the arguments'
pytree structure with every static field (described field by field, never by `repr`),
their shapes and dtypes, JAX's tracing settings, the backend, the versions of JAX,
jaxlib and the libraries traced with them, and the source of every thermojax module. An
argument the key cannot describe (a closure, an object of unknown type) makes the call
an ordinary `equinox.filter_jit` one. Without a compilation cache nothing is stored, and
each program is still compiled once per process, ahead of time.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import os
import pickle
import threading
import types
from importlib import metadata
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

MAX_BYTES = 256 * 1024**2  # least recently used entries go beyond this
_LIBRARIES = ("jax", "jaxlib", "equinox", "lineax", "optimistix", "diffrax", "numpy")
_SETTINGS = ("jax_enable_x64", "jax_numpy_rank_promotion", "jax_numpy_dtype_promotion",
             "jax_default_matmul_precision", "jax_default_prng_impl")


class _Undescribable(Exception):
    """An argument the key cannot describe exactly: the call is not stored."""


# XLA's options for a program run about once per model structure: without LLVM's
# optimizations it compiled 25-40 % faster (PRBS1's smoothed states and free run) and ran
# as fast, once.
_ONCE = {"xla_backend_optimization_level": 0}


def stored_jit(fn=None, *, once: bool = False):
    """`equinox.filter_jit(fn)`, compiled ahead of time once per process and key (threads
    that need the same program wait for one compilation instead of each compiling it),
    its traced program stored across runs while the compilation cache is on
    (`jax_compilation_cache_dir` set). `fn` must return a pytree of arrays. `once`: a
    program run about once per model structure (a fit's summary, a step's score tests),
    whose compilation is most of its cost: compiled without LLVM's optimizations.
    `@stored_jit` or `@stored_jit(once=True)`."""
    if fn is None:
        return functools.partial(stored_jit, once=once)
    jitted = eqx.filter_jit(fn)
    options = _ONCE if once else None
    name = f"{fn.__module__}.{fn.__qualname__}" + (" once" if once else "")

    def program(args):
        """`(compiled, out_tree, dynamic leaves)` for `args`, or None when they cannot
        be keyed (traced, or undescribable)."""
        leaves, treedef = jax.tree.flatten(args)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):  # inside another trace
            return None
        dynamic = [eqx.is_array(x) for x in leaves]
        try:
            key = _key(name, treedef, leaves, dynamic)
        except _Undescribable:
            return None
        compiled, out_tree = _program(key, lambda: _compile(fn, treedef, leaves, dynamic,
                                                            key, options))
        return compiled, out_tree, [x for x, d in zip(leaves, dynamic) if d]

    @functools.wraps(fn)
    def call(*args):
        found = program(args)
        if found is None:
            return jitted(*args)
        compiled, out_tree, arrays = found
        return jax.tree.unflatten(out_tree, compiled(*arrays))

    def ahead(*args) -> None:
        """Compile (or load) the program for arguments shaped like `args` without running
        it: on a background thread, while other compiled work runs."""
        program(args)

    call.ahead = ahead
    return call


def _folder() -> Path | None:
    root = jax.config.jax_compilation_cache_dir
    return None if not root else Path(root) / "traced"


# ---------------------------------------------------------------------------
# The key


def _key(name: str, treedef, leaves, dynamic) -> str:
    h = hashlib.sha256()
    h.update(repr((_environment(), name, jax.default_backend())).encode())
    h.update(_describe_treedef(treedef).encode())
    for x, d in zip(leaves, dynamic):
        h.update((repr((tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False))))
                  if d else _describe(x)).encode())
    return h.hexdigest()


@functools.cache
def _source_digest() -> str:
    """SHA-256 of every thermojax module's source: any change to the code is a new key."""
    root = Path(__file__).resolve().parents[1]  # the thermojax package
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


@functools.cache
def _versions() -> tuple:
    out = []
    for lib in _LIBRARIES:
        try:
            out.append((lib, metadata.version(lib)))
        except metadata.PackageNotFoundError:
            out.append((lib, None))
    return tuple(out)


def _environment() -> tuple:
    settings = tuple((s, str(getattr(jax.config, s))) for s in _SETTINGS)
    return (_source_digest(), _versions(), settings)


def _describe_treedef(treedef) -> str:
    if treedef.num_nodes == 1 and treedef.num_leaves == 1:
        return "*"
    kind, aux = treedef.node_data()
    children = ",".join(_describe_treedef(c) for c in treedef.children())
    return f"{_qualified(kind)}[{_describe(aux)}]({children})"


def _qualified(t) -> str:
    return f"{t.__module__}.{t.__qualname__}"


def _describe(x) -> str:
    """An exact, process-independent description of a static value."""
    if x is None or isinstance(x, (bool, int, str, bytes)):
        return f"{type(x).__name__}:{x!r}"
    if isinstance(x, float):
        return f"float:{x.hex()}"
    if isinstance(x, np.ndarray):
        return f"ndarray:{x.dtype}:{x.shape}:{hashlib.sha256(x.tobytes()).hexdigest()}"
    if isinstance(x, np.generic):
        return f"{x.dtype}:{x.item()!r}"
    if isinstance(x, enum.Enum):
        return f"{_qualified(type(x))}.{x.name}"
    if isinstance(x, type):
        return f"type:{_qualified(x)}"
    if isinstance(x, (tuple, list)):
        return f"{_qualified(type(x))}({','.join(_describe(v) for v in x)})"
    if isinstance(x, dict):
        return "dict{" + ",".join(f"{_describe(k)}:{_describe(v)}" for k, v in x.items()) + "}"
    if isinstance(x, (set, frozenset)):
        return f"{type(x).__name__}{{{','.join(sorted(_describe(v) for v in x))}}}"
    if isinstance(x, types.FunctionType):
        if x.__closure__ or "<" in x.__qualname__:  # closures and lambdas: unknown content
            raise _Undescribable(x)
        return f"function:{_qualified(x)}"
    if dataclasses.is_dataclass(x):
        fields = ",".join(f"{f.name}={_describe(getattr(x, f.name, None))}"
                          for f in dataclasses.fields(x))
        return f"{_qualified(type(x))}({fields})"
    if type(x).__module__.startswith("equinox") and repr(x) == "Missing":
        return "equinox.Missing"  # equinox's placeholder for a dynamic field
    raise _Undescribable(x)


# ---------------------------------------------------------------------------
# The store


_loaded: dict[str, tuple] = {}  # key -> (compiled program, its outputs' treedef)
_locks: dict[str, threading.Lock] = {}
_guard = threading.Lock()


def forget_programs() -> None:
    """Drop this process's compiled programs (`_memory.release_compiled_if_crowded`)."""
    with _guard:
        _loaded.clear()
        _locks.clear()


def _program(key: str, build):
    """This process's program of `key`, built by `build()` once."""
    with _guard:
        lock = _locks.setdefault(key, threading.Lock())
    with lock:  # one thread builds a program; the others wait for it
        if key not in _loaded:
            _loaded[key] = build()
        return _loaded[key]


def _compile(fn, treedef, leaves, dynamic, key: str, options=None):
    """`(fn compiled for the array leaves' shapes with XLA's `options`, its outputs'
    treedef)`: from the traced program stored under `key` if there is one, else traced
    (and stored, with a cache folder)."""
    specs = [jax.ShapeDtypeStruct(x.shape, x.dtype,
                                  weak_type=bool(getattr(x, "weak_type", False)))
             for x, d in zip(leaves, dynamic) if d]
    folder = _folder()
    stored = None
    if folder is not None:
        stored = _load(folder / key) or _store(folder / key, fn, treedef, leaves, dynamic,
                                               specs)
    if stored is not None:
        exported, out_tree = stored
        try:
            return jax.jit(exported.call).lower(*specs).compile(options), out_tree
        except Exception as err:  # a damaged entry that read back: removed, traced again
            _discard(folder / key, f"it could not be compiled ({type(err).__name__})")
    flat, out_tree = _flat(fn, treedef, leaves, dynamic)
    return jax.jit(flat).lower(*specs).compile(options), out_tree[0]


def _flat(fn, treedef, leaves, dynamic):
    """`(fn of the array leaves alone, returning its outputs' leaves; a list that its
    trace fills with the outputs' treedef)`."""
    out_tree = []

    def flat(*arrays):
        it = iter(arrays)
        args = jax.tree.unflatten(treedef, [next(it) if d else x
                                            for x, d in zip(leaves, dynamic)])
        out, tree = jax.tree.flatten(fn(*args))
        out_tree.append(tree)
        return out

    flat.__name__ = flat.__qualname__ = fn.__name__  # compilation logs and profiles name it
    return flat, out_tree


def _discard(path: Path, why: str) -> None:
    """Remove a damaged cache entry, with a warning; the program is traced again."""
    import warnings

    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass
    warnings.warn(f"the compile-cache entry {path} was damaged ({why}); it was removed and "
                  "the program is compiled afresh", RuntimeWarning, stacklevel=3)


def _load(path: Path):
    """`(jax.export.Exported, outputs' treedef)` stored at `path`, or None. An entry that
    exists but fails its content hash or cannot be read back is removed, with a warning."""
    try:
        raw = path.read_bytes()
    except OSError:  # absent or unreadable: trace again
        return None
    try:
        blob = pickle.loads(raw)
        digest = blob.get("sha256")
        if digest is not None and hashlib.sha256(blob["exported"]).hexdigest() != digest:
            raise ValueError("its content hash does not match")
        exported = jax.export.deserialize(blob["exported"])
        out_tree = jax.tree.structure(blob["outputs"])
        os.utime(path)  # recently used
    except Exception as err:
        _discard(path, str(err) if isinstance(err, ValueError) and "hash" in str(err)
                 else f"{type(err).__name__} on reading it")
        return None
    return exported, out_tree


def _store(path: Path, fn, treedef, leaves, dynamic, specs):
    """Trace and export `fn` and write it to `path`: `(Exported, outputs' treedef)`, or
    None if it cannot be exported (e.g. a custom call JAX cannot serialize)."""
    flat, out_tree = _flat(fn, treedef, leaves, dynamic)
    try:
        exported = jax.export.export(jax.jit(flat))(*specs)
        outputs = jax.tree.unflatten(out_tree[0], [jax.ShapeDtypeStruct(a.shape, a.dtype)
                                                   for a in exported.out_avals])
        serialized = bytes(exported.serialize())
        blob = pickle.dumps({"exported": serialized, "outputs": outputs,
                             "sha256": hashlib.sha256(serialized).hexdigest()})
    except Exception:
        return None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}")
        tmp.write_bytes(blob)
        os.replace(tmp, path)
        _evict(path.parent)
    except OSError:  # a read-only or full cache folder: this run still uses the program
        pass
    return exported, out_tree[0]


def _evict(folder: Path) -> None:
    """Delete the least recently used entries while the folder holds over `MAX_BYTES`."""
    entries = sorted((p.stat().st_mtime, p.stat().st_size, p) for p in folder.iterdir()
                     if not p.name.startswith("."))
    total = sum(size for _, size, _ in entries)
    for _, size, path in entries:
        if total <= MAX_BYTES:
            break
        path.unlink(missing_ok=True)
        total -= size
