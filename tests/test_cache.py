"""The persistent compilation cache the command line turns on (issue: compile once, not every
run): where it goes, how it is turned off."""

import time

import jax

from jaxtable._cache import cache_directory, enable_compilation_cache
from jaxtable.cli import build_parser


def test_cache_directory_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXTABLE_CACHE_DIR", str(tmp_path / "c"))
    assert cache_directory() == tmp_path / "c"
    monkeypatch.setenv("JAXTABLE_CACHE_DIR", "off")
    assert cache_directory() is None
    assert enable_compilation_cache() is None
    monkeypatch.delenv("JAXTABLE_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_directory() == tmp_path / "xdg" / "jaxtable" / "jax"


def test_enable_sets_the_jax_cache_and_the_cli_can_turn_it_off(tmp_path):
    old = jax.config.jax_compilation_cache_dir
    try:
        path = enable_compilation_cache(tmp_path / "jc")
        assert path.is_dir() and jax.config.jax_compilation_cache_dir == str(path)
    finally:
        jax.config.update("jax_compilation_cache_dir", old)
    assert build_parser().parse_args(["--no-cache", "spiral"]).no_cache
    assert not build_parser().parse_args(["spiral"]).no_cache


def test_the_cache_is_locked_for_processes_that_share_it(tmp_path):
    """JAX writes a cache entry in place; only with a size limit does it lock the directory
    around reads and writes (its `.lockfile`), so a process sharing the cache never reads a
    half-written entry. A fresh process: the cache, once initialised, stays as it is."""
    import subprocess
    import sys

    code = (
        "import jax, jax.numpy as jnp; jax.config.update('jax_enable_x64', True);"
        "from jaxtable._cache import MAX_BYTES, enable_compilation_cache;"
        f"enable_compilation_cache({str(tmp_path / 'jc')!r});"
        "assert jax.config.jax_compilation_cache_max_size == MAX_BYTES > 0;"
        "jax.jit(lambda x: jnp.sin(x) * 2.0)(jnp.ones(3)).block_until_ready()"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    files = {p.name for p in (tmp_path / "jc").iterdir()}
    assert ".lockfile" in files
    assert any(name.endswith("-cache") for name in files), files


def test_entries_without_an_access_time_get_one(tmp_path):
    """An entry written with no size limit has no access-time file, and JAX's eviction scan
    would then fail every later write: enabling the cache adds the missing ones."""
    from jaxtable._cache import _add_missing_access_times

    d = tmp_path / "jc"
    d.mkdir()
    (d / "jit_f-abc-cache").write_bytes(b"x")
    (d / "jit_g-def-cache").write_bytes(b"y")
    (d / "jit_g-def-atime").write_bytes((7).to_bytes(8, "little"))
    assert _add_missing_access_times(d) == 1
    assert (d / "jit_f-abc-atime").stat().st_size == 8
    assert (d / "jit_g-def-atime").read_bytes() == (7).to_bytes(8, "little")  # kept
    assert _add_missing_access_times(d) == 0


def _lru(path, limit):
    from jax._src.lru_cache import LRUCache

    from jaxtable._cache import _install_running_total

    assert _install_running_total()
    return LRUCache(str(path), max_size=limit)


def test_the_size_limit_still_evicts_the_least_recently_used(tmp_path):
    """With the running total in place of JAX's per-write listing, a cache past its limit
    is trimmed as JAX trims it: least recently used entries first, the directory within the
    limit after every write."""
    cache = _lru(tmp_path, 5_000)
    for i in range(4):
        cache.put(f"k{i}", bytes(1_000))
        time.sleep(0.002)  # distinct access times
    for i in range(4, 9):
        assert cache.get("k0") is not None  # the oldest write, but always just used
        time.sleep(0.002)
        cache.put(f"k{i}", bytes(1_000))
        assert sum(p.stat().st_size for p in tmp_path.glob("*-cache")) <= 5_000
    left = sorted(p.name.removesuffix("-cache") for p in tmp_path.glob("*-cache"))
    assert left == ["k0", "k5", "k6", "k7", "k8"], left


def test_writes_under_the_limit_list_the_directory_once_per_rescan(tmp_path, monkeypatch):
    """JAX listed the whole directory and read every access time on every write; now the
    sizes are listed on the first write and after every RESCAN_WRITES writes."""
    from jaxtable import _cache

    cache = _lru(tmp_path, 1 << 30)
    listings = []
    sizes = _cache._entry_bytes
    monkeypatch.setattr(_cache, "_entry_bytes", lambda p: listings.append(p) or sizes(p))
    n = 2 * _cache.RESCAN_WRITES + 2
    for i in range(n):
        cache.put(f"k{i}", bytes(10))
    assert len(listings) == 3  # writes 1, RESCAN_WRITES + 1 and 2 RESCAN_WRITES + 1
    assert len(list(tmp_path.glob("*-cache"))) == n  # nothing evicted
