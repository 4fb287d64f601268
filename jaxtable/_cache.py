"""JAX's persistent compilation cache for jaxtable's programs.

A calibration or a diagnosis spends most of its first run compiling; the compiled programs
depend only on the shapes of the data (rows, measured columns), so a second run on a file
of the same shape can load them from disk instead. The command line turns the cache on by
default (`jaxtable --no-cache VERB ...` turns it off); library users call
`enable_compilation_cache()` once.

Where: `$JAXTABLE_CACHE_DIR` if set (the value `off` turns the cache off), else
`$XDG_CACHE_HOME/jaxtable/jax`, else `~/.cache/jaxtable/jax`. Every program is stored,
the small ones too: a diagnosis compiles ~160 programs under half a second each, 5 s in
all, and loading them is cheaper (the bundled example's cache is ~2 MB). The directory
may be deleted at any time.

Several processes may share the directory (two runs at once, the test workers): JAX writes
an entry in place, and a process that reads a half-written entry crashes in the
deserialiser (a segfault, seen with two test workers). With a size limit set, JAX holds a
file lock (`filelock`) around every read and write and evicts the least recently used
entries past `MAX_BYTES`, so the cache is always set with one. That eviction needs an
access-time file beside every entry; entries written without one (by a process with no
limit, or before this rule) would make every later write fail, so enabling the cache adds
the missing ones.

JAX checks the limit on every write by listing the whole directory and reading every
entry's access time (~20 µs an entry: 26 ms a write with 1,400 entries, 100 ms with 5,000;
the bundled example's first `jaxtable diagnose` writes 63 programs and took 20–21 s instead
of 13–14 s in a cache that already held 5,000 entries).
`enable_compilation_cache` replaces that check, in this process, by one that keeps a
running total of the directory's size (`_Sizes`): it lists the directory (sizes only) on
the first write and after every `RESCAN_WRITES` writes, adds each write's size in between,
and runs JAX's own eviction when the total passes the limit. Writes by other processes in
between are counted at the next listing, so the limit may be passed by what they wrote
meanwhile.
"""

import os
import threading
import time
from pathlib import Path

import jax

MAX_BYTES = 4 << 30  # the limit that turns on JAX's file lock (and its LRU eviction)
RESCAN_WRITES = 64  # writes between two listings of the directory's sizes
_ENTRY, _ATIME = "-cache", "-atime"  # JAX's file suffixes (jax/_src/lru_cache.py)


def _entry_bytes(path: Path) -> int:
    """Total size of the cache entries in `path` (bytes)."""
    total = 0
    for entry in path.glob(f"*{_ENTRY}"):
        try:
            total += entry.stat().st_size
        except OSError:  # evicted by another process meanwhile
            pass
    return total


class _Sizes:
    """This process's running total of each cache directory's size (module docstring)."""

    def __init__(self):
        self.total: dict = {}  # directory -> (bytes, writes since the last listing)
        self.lock = threading.Lock()

    def over_limit(self, path: Path, adding: int, limit: int) -> bool:
        """Count a write of `adding` bytes; whether the directory would pass `limit`."""
        with self.lock:
            size, writes = self.total.get(path, (None, 0))
            if size is None or writes >= RESCAN_WRITES:
                size, writes = _entry_bytes(path), 0
            self.total[path] = (size + adding, writes + 1)
            return size + adding > limit

    def evicted(self, path: Path) -> None:
        """The directory was trimmed: list it again at the next write."""
        with self.lock:
            self.total.pop(path, None)


_SIZES = _Sizes()


def _install_running_total() -> bool:
    """Replace JAX's per-write eviction check (`LRUCache._evict_if_needed`) by `_SIZES`'s,
    which calls JAX's own eviction when the directory passes its limit. Returns whether
    it is in place (False where this JAX has no such method: its own rule then applies)."""
    try:
        from jax._src import lru_cache
    except ImportError:
        return False
    cls = getattr(lru_cache, "LRUCache", None)
    full = getattr(cls, "_evict_if_needed", None)
    if full is None:
        return False
    if getattr(full, "_running_total", False):
        return True

    def evict_if_needed(self, *, additional_size: int = 0) -> None:
        if not getattr(self, "eviction_enabled", True):
            return
        if "://" in str(self.path):  # a remote cache (gs://...): JAX's own check
            full(self, additional_size=additional_size)
            return
        path = Path(self.path)
        if _SIZES.over_limit(path, additional_size, self.max_size):
            full(self, additional_size=additional_size)
            _SIZES.evicted(path)

    evict_if_needed._running_total = True
    cls._evict_if_needed = evict_if_needed
    return True


def _add_missing_access_times(path: Path) -> int:
    """Write an access-time file (now, 8 bytes little-endian ns, as JAX does) for every
    entry in `path` that has none; returns how many were added."""
    now = time.time_ns().to_bytes(8, "little")
    added = 0
    for entry in path.glob(f"*{_ENTRY}"):
        atime = path / (entry.name.removesuffix(_ENTRY) + _ATIME)
        if not atime.exists():
            try:
                atime.write_bytes(now)
                added += 1
            except OSError:
                pass
    return added


def cache_directory() -> Path | None:
    """The cache directory the environment asks for (None: turned off)."""
    env = os.environ.get("JAXTABLE_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("off", "0", "none", "") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxtable" / "jax"


def enable_compilation_cache(directory: str | os.PathLike | None = None) -> Path | None:
    """Turn on the persistent compilation cache in `directory` (default `cache_directory()`);
    returns the directory used, or None when it is turned off or cannot be created (the
    programs are then compiled as usual)."""
    path = Path(directory) if directory is not None else cache_directory()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    _add_missing_access_times(path)
    _install_running_total()
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
