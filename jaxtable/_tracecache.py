"""Traced programs kept on disk beside the compilation cache, so that a repeat run skips
tracing as well as compiling.

JAX's persistent compilation cache (`_cache.py`) keeps compiled programs, but a new process
still traces and lowers every program before it can look the compiled one up: a repeat
`jaxtable diagnose` spent ~10 s of its ~22 s tracing its shared fit program. `jax.export`
serialises a traced and lowered program; `call` stores one per program and argument
signature in `<compilation cache>/traced/` and runs the stored one instead of tracing.

The key is everything tracing depends on: the function (module and name); a fingerprint of
jaxtable's source files and of the versions of Python and of the libraries that trace
(jax, jaxlib, equinox, optimistix, lineax, numpy); the backend, the x64 flag and the
compiler options; and the arguments, split as `eqx.filter_jit` splits them: the shape,
dtype and weak type of every array, and the pickled bytes of everything else (tables'
static fields, effect sets, layouts, Python numbers, the pytree structure). A program is
traced as before, and nothing stored, when the function is not one of jaxtable's
module-level functions (found by its module and name), when the
static arguments hold a function or class from outside jaxtable and the libraries above
(its code is not in the fingerprint), when they cannot be pickled, when an array is
sharded over several devices, or when the program cannot be exported.

On by default wherever the compilation cache is (the command line, the tests, a library
user's `enable_compilation_cache()`); `$JAXTABLE_TRACE_CACHE=0` turns it off. The
directory holds at most `MAX_BYTES` (least recently used entries go first) and may be
deleted at any time.
"""

import functools
import hashlib
import importlib.metadata
import inspect
import io
import os
import pickle
import sys
import threading
import types
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
from jax import export

from ._errors import env_switch

ENV = "JAXTABLE_TRACE_CACHE"
MAX_BYTES = 512 << 20
SUFFIX = ".jaxexport"
_LIBRARIES = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy")
_TRUSTED = ("jaxtable", "jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy", "builtins")
_TRUSTED += ("functools", "collections", "operator", "math", "typing", "enum", "types", "abc")

_MEMORY: dict = {}  # key -> (compiled caller, output structure): one process's programs
_REFUSED: set = set()  # keys whose program could not be exported
_LOCKS: dict = {}  # key -> lock held while its program is loaded or traced
_GUARD = threading.Lock()  # guards _LOCKS
_REPEATS: dict = {}  # call signature -> (key, its objects, its arrays' types): `_repeat`
MAX_REPEATS = 1024


def directory() -> Path | None:
    """Where traced programs are stored: `traced/` in the compilation cache directory, or
    None (the compilation cache is off, or `$JAXTABLE_TRACE_CACHE` is 0)."""
    base = jax.config.jax_compilation_cache_dir
    return Path(base) / "traced" if env_switch(ENV, "off", "on") and base else None


@functools.cache
def fingerprint() -> str:
    """SHA-256 of jaxtable's source files and the versions of Python and the libraries."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    for dist in _LIBRARIES:
        try:
            h.update(f"{dist}={importlib.metadata.version(dist)}\0".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{dist}=?\0".encode())
    h.update(sys.version.encode())
    return h.hexdigest()


class _Untrusted(Exception):
    """A function or class from outside the fingerprinted code is in the arguments."""


def _trusted(module: str | None) -> bool:
    return (module or "").split(".")[0] in _TRUSTED


def _named(fun) -> bool:
    """Whether `fun` is jaxtable's module-level function of its name (itself, or what that
    name's object wraps, through a chain of `__wrapped__` as `functools.wraps` leaves it:
    `_jit.jit`'s wrapper, and a type checker's around that): only then do its module and
    name identify its code (a `jax.vmap(f)` carries f's name, and two such wrappers of f
    could differ)."""
    module = getattr(fun, "__module__", None) or ""
    if module.split(".")[0] != "jaxtable":
        return False
    obj = getattr(sys.modules.get(module), getattr(fun, "__qualname__", ""), None)
    try:
        return inspect.unwrap(obj, stop=lambda f: f is fun) is fun
    except ValueError:  # a cycle of `__wrapped__`
        return False


class _KeyPickler(pickle.Pickler):
    """Pickles the static arguments for the key; refuses code from outside `_TRUSTED`
    (pickle stores a function or class by name, not by code)."""

    def reducer_override(self, obj):
        if isinstance(obj, (type, types.FunctionType, types.BuiltinFunctionType)):
            if not _trusted(getattr(obj, "__module__", None)):
                raise _Untrusted(repr(obj))
        elif isinstance(obj, functools.partial):
            if not _trusted(getattr(obj.func, "__module__", None)):
                raise _Untrusted(repr(obj))
        return NotImplemented


def _static_bytes(obj) -> bytes | None:
    buffer = io.BytesIO()
    pickler = _KeyPickler(buffer, protocol=5)
    # no memo: the bytes must not depend on which equal objects happen to be one object
    # (a value loaded from a stored program's outputs is a copy where a traced one was
    # shared, and the next call's key would differ)
    pickler.fast = True
    try:
        pickler.dump(obj)
    except Exception:  # _Untrusted, or anything pickle cannot store
        return None
    return buffer.getvalue()


def _slots(leaves) -> list:
    return [_Slot(i) for i in range(len(leaves))]


def _avals(xs) -> tuple:
    """(shape, dtype, weak type) of each array. One call for all of a call's arrays: the
    repeat path (`_repeat`) compares them on every call, ~70 arrays for a fit's block (read
    as attributes: 34 µs for 85 arrays, where numpy's `np.shape` and `np.dtype` took 78). A
    leaf that is not an array (a Python number where an earlier call had an array) gets its
    type's name, which no array's dtype equals."""
    return tuple(_aval(x) for x in xs)


def _aval(x) -> tuple:
    try:
        return x.shape, x.dtype.str, bool(getattr(x, "weak_type", False))
    except AttributeError:  # not an array
        return np.shape(x), type(x).__name__, False


def _sharded(xs) -> bool:
    """Whether any of the arrays is spread over several devices."""
    return any(isinstance(x, jax.Array) and len(x.sharding.device_set) > 1 for x in xs)


def _key(fun, options: dict, leaves, static_bytes: bytes) -> str:
    h = hashlib.sha256()
    parts = (
        fingerprint(),
        f"{fun.__module__}.{fun.__qualname__}",
        jax.default_backend(),
        str(jax.config.jax_enable_x64),
        repr(sorted(options.items())),
        repr(list(_avals(leaves))),
    )
    for part in parts:
        h.update(part.encode() + b"\0")
    h.update(static_bytes)
    return h.hexdigest()


def _caller(exported, options: dict, name: str):
    """The stored program, compiled under `name` (`_name`: so that compile logs, profiles
    and the compilation cache's entries name the function it was traced from)."""

    def run(*args):
        return exported.call(*args)

    run.__name__ = run.__qualname__ = name
    return jax.jit(run, **({"compiler_options": options} if options else {}))


class _Slot:
    """Stands for the `index`-th array of a program's outputs in its stored output pytree
    (a pytree whose structure is pickled as objects: JAX's pickled tree structures do not
    restore every node type, equinox's enumerations among them)."""

    def __init__(self, index: int):
        self.index = index


def _fill(template, arrays):
    return jax.tree.map(lambda x: arrays[x.index] if isinstance(x, _Slot) else x, template)


def _load(path: Path, options: dict, name: str):
    try:
        blob, template = pickle.loads(path.read_bytes())
        exported = export.deserialize(bytearray(blob))
    except Exception:  # absent, half-written by another process, or from another version
        return None
    try:
        os.utime(path)  # recently used
    except OSError:
        pass
    return _caller(exported, options, name), template


def _name(fun, static) -> str:
    """The program's name: the function's, joined by the name of a function passed as its
    first argument (`run_batch`'s kernels are all `_vmap(fn, ...)`)."""
    name = getattr(fun, "__name__", "program")
    args = static[0]
    inner = getattr(args[0], "__name__", None) if args and callable(args[0]) else None
    return f"{name}_{inner}" if inner else name


def _export(fun, static, treedef, leaves, options: dict):
    """Trace and lower `fun` on the arguments' signature; (exported, output template: the
    output pytree with `_Slot`s where the program returns arrays)."""
    structure = {}

    def flat(*dynamic):
        args, kwargs = eqx.combine(jax.tree.unflatten(treedef, dynamic), static)
        leaves, out_treedef = jax.tree.flatten(fun(*args, **kwargs))
        arrays = [x for x in leaves if eqx.is_array(x)]
        slots = iter(range(len(arrays)))
        template = [_Slot(next(slots)) if eqx.is_array(x) else x for x in leaves]
        structure["template"] = jax.tree.unflatten(out_treedef, template)
        return arrays

    specs = [
        jax.ShapeDtypeStruct(shape, np.dtype(dtype), weak_type=weak)
        for shape, dtype, weak in _avals(leaves)
    ]
    exported = export.export(jax.jit(flat), disabled_checks=_unstable_targets())(*specs)
    return exported, structure["template"]


@functools.cache
def _unstable_targets() -> tuple:
    """Export's permission for the CPU's LAPACK kernels that JAX does not promise to keep
    stable across versions (`lapack_dormqr_ffi`, which lineax's QR solve in optimistix's
    Levenberg-Marquardt calls, among them): a stored program is keyed on the jaxlib version
    that traced it, so only that version loads it. Without it such a program was traced
    once for the refused export and again for the plain call, in every process."""
    try:
        from jax._src.lib import lapack

        names = {name for regs in lapack.registrations().values() for name, *_ in regs}
    except Exception:  # another jaxlib's layout: export refuses them, and they trace as before
        return ()
    return tuple(export.DisabledSafetyCheck.custom_call(name) for name in sorted(names))


def _store(folder: Path, path: Path, exported, out) -> None:
    """Write atomically (another process may read the entry while it is written), then
    keep the folder under MAX_BYTES by dropping the least recently used entries."""
    try:
        data = pickle.dumps((exported.serialize(), out), protocol=5)
        folder.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, path)
        entries = sorted(folder.glob(f"*{SUFFIX}"), key=lambda p: p.stat().st_mtime)
        total = sum(p.stat().st_size for p in entries)
        for p in entries[:-1]:
            if total <= MAX_BYTES:
                break
            total -= p.stat().st_size
            p.unlink(missing_ok=True)
    except Exception:  # a full disk, a read-only cache, an output pickle cannot store
        pass


def _entry(key: str, fun, static, treedef, leaves, options: dict, folder: Path):
    """The (caller, output template) of `key`, loaded or traced and stored, or None where the
    program cannot be exported. One thread at a time per key: the per-core pieces of a batch
    (`_batch._Part`) call the same new program at once, and each would trace it and compile
    its own caller (JAX compiles one jitted function once for threads that call it at once,
    but these would be two functions)."""
    with _GUARD:
        lock = _LOCKS.setdefault(key, threading.Lock())
    with lock:
        entry = _MEMORY.get(key)
        if entry is not None or key in _REFUSED:
            return entry
        path, name = folder / f"{key}{SUFFIX}", _name(fun, static)
        entry = _load(path, options, name)
        if entry is None:
            try:
                exported, out = _export(fun, static, treedef, leaves, options)
            except Exception:  # not exportable (e.g. a host callback): trace as usual
                _REFUSED.add(key)
                return None
            _store(folder, path, exported, out)
            entry = _caller(exported, options, name), out
        _MEMORY[key] = entry
        return entry


def _repeat(fun, options: dict, args: tuple, kwargs: dict):
    """(signature, leaves, key or None) of a call: the key when the call repeats an earlier
    one's signature (`_REPEATS`), or None. The signature is the function, the options, the
    pytree structure of the arguments (static fields included) and what the key's other
    parts depend on; a repeat also has the same objects (`is`) where the earlier call had
    objects that are not arrays, and arrays of the same shapes and types. Those objects are
    kept alive with the record, so that no other object can take their identity."""
    leaves, treedef = jax.tree.flatten((args, kwargs))
    try:
        sig = (fun, tuple(sorted(options.items())), treedef, fingerprint())
        sig += (jax.default_backend(), jax.config.jax_enable_x64)
        record = _REPEATS.get(sig)
    except Exception:  # a static field that cannot be hashed or compared
        return None, leaves, None
    if record is None:
        return sig, leaves, None
    key, objects, (index, avals) = record
    if all(leaves[i] is x for i, x in objects):
        arrays = [leaves[i] for i in index]
        if _avals(arrays) == avals and not _sharded(arrays):
            return sig, leaves, key
    return sig, leaves, None


def _remember(sig, leaves, key: str) -> None:
    if sig is None:
        return
    if len(_REPEATS) >= MAX_REPEATS:
        _REPEATS.clear()
    objects = tuple((i, x) for i, x in enumerate(leaves) if not eqx.is_array(x))
    index = tuple(i for i, x in enumerate(leaves) if eqx.is_array(x))
    _REPEATS[sig] = (key, objects, (index, _avals([leaves[i] for i in index])))


def _run(entry, leaves):
    run, template = entry
    # a device array committed to a device as a host array: its placement is part of the
    # stored program's call signature, and a second placement compiled the program again.
    # Uncommitted ones (jnp.asarray, the outputs of programs called without placement)
    # share the host arrays' signature and are passed as they are: a fit's block call of
    # ~70 arrays skips copying them to the device again (a call 0.47 → 0.28 ms for 70
    # small arrays; the test written inline: it runs for every array of every call)
    inputs = [
        x
        if getattr(x, "weak_type", False) or (isinstance(x, jax.Array) and not x.committed)
        else np.asarray(x)
        for x in leaves
    ]
    return _fill(template, run(*inputs))


def call(fun, options: dict, args: tuple, kwargs: dict, plain):
    """`fun(*args, **kwargs)` through its stored traced program (exported and stored on
    first use), or `plain()` (the usual compiled call) where the module docstring says.

    A call that repeats an earlier one (`_repeat`: the same static objects, arrays of the
    same shapes) finds its program without pickling the arguments for the key: ~0.3 ms
    instead of 2.5–4.5 ms for a fit's block of stops (`_calibration.fit`), which is called
    several times a step."""
    folder = directory()
    if folder is None or not _named(fun):
        return plain()
    sig, all_leaves, key = _repeat(fun, options, args, kwargs)
    entry = _MEMORY.get(key) if key is not None else None
    if entry is not None:
        return _run(entry, [x for x in all_leaves if eqx.is_array(x)])
    dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    # the key pickles the arguments as objects, each array replaced by its place
    static_bytes = _static_bytes(eqx.combine(jax.tree.unflatten(treedef, _slots(leaves)), static))
    if static_bytes is None or _sharded(leaves):
        return plain()
    key = _key(fun, options, leaves, static_bytes)
    entry = _MEMORY.get(key) or _entry(key, fun, static, treedef, leaves, options, folder)
    if entry is None:
        return plain()
    _remember(sig, all_leaves, key)
    return _run(entry, leaves)
