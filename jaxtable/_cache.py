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
"""

import os
import time
from pathlib import Path

import jax

MAX_BYTES = 4 << 30  # the limit that turns on JAX's file lock (and its LRU eviction)
_ENTRY, _ATIME = "-cache", "-atime"  # JAX's file suffixes (jax/_src/lru_cache.py)


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
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
