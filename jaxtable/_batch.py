"""Batching: apply a one-row function over a batch in bounded-memory chunks, spread over every
device of this process and over every process of a `jax.distributed` job.

`run_batch(fn, shared, batched, chunk=...)` is the one entry point the batch APIs use
(commands, forward kinematics, sensitivities, error maps, Monte Carlo, the simulator):

- inside `jit` / `grad` (traced input): `jax.vmap`, or `jax.lax.map` over chunks beyond
  `chunk` rows, so peak memory is one chunk's;
- concrete input: a loop over equal chunks of at most about `chunk` rows (the next chunk is
  dispatched before the previous one is copied out), each chunk one call of a compiled
  `vmap`. The chunk size is rounded up (`chunk_rows`: a power of two of at least
  `SMALL_BATCH` rows for a small batch, a multiple of chunk/16 otherwise; the last chunk is
  padded by repeating its last row), so batches of different sizes share a few compiled
  shapes. Chunks under `_jit.LARGE_BATCH` rows compile quick (XLA's classic emitters: their
  compile time is the wait), larger ones with XLA's default emitters (they stream: run time
  is the wait);
- large chunks on the CPU (one device): each chunk is cut into one piece per core, and the
  pieces run at once from a pool of host threads (XLA runs programs called from different
  threads concurrently), each piece a `lax.map` over blocks of `BLOCK` rows with a vmap
  inside (`_blocked`), so that a block's intermediate values stay in its core's cache. A
  vmap over a whole chunk instead writes every intermediate value of every row to memory
  and reads it back in the next fusion, and XLA splits each fusion over the cores. Measured
  on 2 cores (the error map's kernel without the condition number, 2¹⁹ poses): 5.3×10⁵
  poses/s as vmapped chunks of 8192, 1.15×10⁶ in pieces of 128-row blocks. `stream_batch`
  keeps the cores busy over a sequence of chunks while the caller reduces the finished ones
  (error and command maps);
- several local devices (GPUs, or `--xla_force_host_platform_device_count`): each chunk is
  placed with `NamedSharding` over a 1-D mesh of all local devices (`AxisType.Auto`), and the
  jitted vmap is partitioned by XLA, one slice of rows per device;
- several processes (`jax.distributed.initialize`): every process calls the API with the same
  full input, computes its own contiguous slice of rows on its local devices, and the slices
  are gathered with `process_allgather`, so every process returns the full result.

No `shard_map` (optimistix/lineax do not support it in this stack) and no LAPACK call in the
batched kernels (simulated CPU devices can deadlock in them; see `_linalg`).
"""

import functools
import math
import os
import threading
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._errors import is_concrete
from ._jit import LARGE_BATCH, jit

DEFAULT_CHUNK = 1 << 16
# the fewest rows a compiled single-chunk batch has (`chunk_rows`): every batch of up to 256
# rows runs one program. A kernel's compilation takes seconds; 256 rows of a per-pose kernel
# run in about a millisecond (forward kinematics ~4 µs a pose on 2 cores), so the padding
# costs nothing a user waits for, and each distinct small size would cost a compilation
SMALL_BATCH = 256


def map_batch(fn, *xs, chunk: int = DEFAULT_CHUNK):
    """`jax.vmap(fn)(*xs)` over the leading axis of every x (pytrees allowed), in chunks.

    Up to `chunk` rows: one vmap. Beyond: `jax.lax.map` with `batch_size=chunk`, so peak
    memory is that of one chunk whatever the batch size. For use inside traced code; from
    Python, `run_batch` is faster and shards.
    """
    n = jax.tree.leaves(xs)[0].shape[0]
    if n <= chunk:
        return jax.vmap(fn)(*xs)
    return jax.lax.map(lambda a: fn(*a), xs, batch_size=chunk)


def flatten_batch(x, tail: int):
    """Reshape (..., *tail_shape) -> (N, *tail_shape); returns (flat, batch_shape). float64;
    numpy where `x` is concrete (no eager programs: `_jit.device_array`), else jnp."""
    xp = np if is_concrete(x) else jnp
    x = xp.asarray(x, dtype=np.float64)
    batch_shape = x.shape[: x.ndim - tail]
    return x.reshape((-1,) + x.shape[x.ndim - tail :]), batch_shape


def _vmap(fn, shared, batched):
    return jax.vmap(partial(fn, shared))(batched)


# the same program two ways (`_jit`): XLA's default emitters for the kernels that stream
# large batches, quick compilation for the small ones, which run once or a few times
_vmapped = eqx.filter_jit(_vmap)
_vmapped_quick = jit(_vmap)


def _vmapped_for(rows: int):
    return _vmapped if rows >= LARGE_BATCH else _vmapped_quick


BLOCK = 128
"""Rows a CPU core works through at a time in a large batch (`_blocks`): a block of the error
map's kernel (~1,100 intermediate values a row) keeps its working set in the core's cache.
Blocks of 32–512 rows measured within the noise of each other (forward kinematics, inverse
kinematics, error maps, sensitivities; 2 cores)."""


def _blocks(fn, shared, batched):
    """`_vmap` as a loop over blocks of `BLOCK` rows (the rows a multiple of BLOCK)."""
    n = jax.tree.leaves(batched)[0].shape[0]
    blocks = jax.tree.map(lambda x: x.reshape((n // BLOCK, BLOCK) + x.shape[1:]), batched)
    out = jax.lax.map(partial(_vmap, fn, shared), blocks)
    return jax.tree.map(lambda x: x.reshape((n,) + x.shape[2:]), out)


_blocked = eqx.filter_jit(_blocks)


def cpu_workers() -> int:
    """Host threads that run a large batch's pieces at once on the CPU: the cores this
    process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@functools.cache
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(workers, thread_name_prefix="jaxtable-batch")


def _in_pieces() -> bool:
    """Whether concrete batches run as per-core pieces (`_Part`): one CPU device, one process."""
    return (
        jax.process_count() == 1
        and len(jax.local_devices()) == 1
        and jax.local_devices()[0].platform == "cpu"
    )


def _quarter_octave(x: int) -> int:
    """The smallest m·2^k ≥ x with m in {4, 5, 6, 7}: four sizes an octave (at most 25 %
    padding), so that batches of many sizes share a few compiled shapes."""
    if x <= 4:
        return max(x, 1)
    k = max(0, (x - 1).bit_length() - 3)
    return ((x + (1 << k) - 1) >> k) << k


def piece_rows(n: int, chunk: int, workers: int) -> int:
    """Rows of each per-core piece of a large batch of `n` rows (`_Part`): the batch shared
    among `workers`, rounded up to four sizes an octave (`_quarter_octave`) and to a
    multiple of BLOCK, at most the largest power of two ≤ chunk / workers (a batch beyond
    that runs as more pieces of that size, two a worker in flight). Sizes by hand in
    `tests/test_batch.py`."""
    cap = 1 << max(BLOCK, chunk // workers).bit_length() - 1
    share = _quarter_octave(math.ceil(n / workers))
    return min(cap, BLOCK * math.ceil(share / BLOCK))


class _Part:
    """One batch (numpy leaves, n rows) computed as pieces on the pool: a large batch in
    pieces of equal rows (a multiple of `BLOCK`, the last padded), each piece's outputs
    written into the part's numpy arrays by the thread that computed it; a small batch as
    one quick-compiled vmap (`chunk_rows`), in one task."""

    def __init__(self, fn, shared, batched, chunk: int, min_rows: int, workers: int):
        self.n = jax.tree.leaves(batched)[0].shape[0]
        size = chunk_rows(max(self.n, 1), chunk, 1, min_rows)
        if size >= LARGE_BATCH:
            size = piece_rows(self.n, chunk, workers)
            kernel = _blocked
        else:
            kernel = _vmapped_quick
        self.batched, self.out, self.treedef = batched, None, None
        self._lock = threading.Lock()
        pool = _pool(workers)
        self.tasks = [
            (
                start,
                min(size, self.n - start),
                pool.submit(self._run, kernel, fn, shared, start, size),
            )
            for start in range(0, max(self.n, 1), size)  # an empty batch: one empty piece
        ]

    def _run(self, kernel, fn, shared, start: int, size: int):
        part = self.batched
        if self.n:
            part = _pad_rows(_slice_rows(part, start, start + size), size)
        leaves, treedef = jax.tree.flatten(kernel(fn, shared, part))
        leaves = [np.asarray(x) for x in leaves]
        with self._lock:
            if self.out is None:
                self.out = [np.empty((self.n,) + x.shape[1:], dtype=x.dtype) for x in leaves]
                self.treedef = treedef
        m = min(size, self.n - start)
        for o, x in zip(self.out, leaves):
            o[start : start + m] = x[:m]

    def result(self, bar=None):
        """The outputs (numpy pytree), once every piece is done (`bar`: a progress bar to
        advance). A piece's error (or an interrupt while waiting) cancels the pieces not yet
        started and is raised."""
        try:
            for _, m, fut in self.tasks:
                fut.result()
                if bar is not None:
                    bar.update(m)
        except BaseException:
            self.cancel()
            raise
        self.batched = None
        return jax.tree.unflatten(self.treedef, self.out)

    def cancel(self):
        """Drop the pieces not yet started (those running finish)."""
        for _, _, fut in self.tasks:
            fut.cancel()


def stream_batch(fn, shared, parts, *, chunk: int = DEFAULT_CHUNK, min_rows=SMALL_BATCH):
    """`(part, run_batch(fn, shared, part, chunk=chunk))` for each part of the iterable
    `parts` (concrete pytrees of rows), in order, with numpy outputs. On one CPU device the
    next parts are computed while the caller works on the one yielded (up to two pieces a
    core ahead), so a loop that reduces each part on the host keeps the cores busy."""
    if not _in_pieces():
        for part in parts:
            yield (
                part,
                jax.tree.map(
                    np.asarray, run_batch(fn, shared, part, chunk=chunk, min_rows=min_rows)
                ),
            )
        return
    workers = cpu_workers()
    ahead = deque()
    try:
        for part in parts:
            part_np = jax.tree.map(np.asarray, part)
            ahead.append((part, _Part(fn, shared, part_np, chunk, min_rows, workers)))
            while sum(len(p.tasks) for _, p in ahead) > 2 * workers and len(ahead) > 1:
                done, p = ahead.popleft()
                yield done, p.result()
        while ahead:
            done, p = ahead.popleft()
            yield done, p.result()
    finally:  # the caller stopped early (an error, an interrupt, a break): drop the rest
        for _, p in ahead:
            p.cancel()


@eqx.filter_jit
def _chunked(fn, shared, batched, chunk):
    return map_batch(partial(fn, shared), batched, chunk=chunk)


def batch_mesh():
    """1-D mesh ("batch",) over this process's devices, or None with a single device."""
    devices = jax.local_devices()
    if len(devices) == 1:
        return None
    return jax.sharding.Mesh(
        np.array(devices), ("batch",), axis_types=(jax.sharding.AxisType.Auto,)
    )


def _pad_rows(tree, n_to: int):
    """Pad every leaf (numpy) along axis 0 to n_to rows by repeating its last row."""
    return jax.tree.map(
        lambda x: (
            x
            if x.shape[0] == n_to
            else np.concatenate([x, np.repeat(x[-1:], n_to - x.shape[0], axis=0)])
        ),
        tree,
    )


def _slice_rows(tree, start: int, stop: int):
    return jax.tree.map(lambda x: x[start:stop], tree)


def chunk_rows(n: int, chunk: int, n_dev: int = 1, min_rows: int = SMALL_BATCH) -> int:
    """Rows of each compiled chunk for a batch of `n` rows (a multiple of `n_dev`), so that
    batches of different sizes share a few compiled shapes:

    - several chunks: equal chunks (little padding), their size rounded up to a multiple of
      chunk/16;
    - one chunk under `_jit.LARGE_BATCH` rows: the next power of two, at least `min_rows`
      (`SMALL_BATCH` unless a caller's rows are costly), at most `chunk`: such batches are
      compile-bound (a forward solve of 1000 poses runs in milliseconds after seconds of
      compilation), so 1, 150 and 200 rows share one program and the padding costs a
      millisecond;
    - one larger chunk: a multiple of chunk/16 (run time is the wait there).
    """
    n_chunks = math.ceil(n / chunk)
    quantum = n_dev * max(1, math.ceil(chunk / 16 / n_dev))
    if n_chunks == 1 and n < LARGE_BATCH:
        bucket = min(max(min_rows, 1 << (n - 1).bit_length()), max(chunk, n))
        return n_dev * math.ceil(bucket / n_dev)
    return quantum * math.ceil(math.ceil(n / n_chunks) / quantum)


def _progress_bar(n: int, progress):
    """A progress bar over `n` rows (`progress`: its description, True, or falsy for a
    disabled one)."""
    from tqdm.auto import tqdm

    desc = progress if isinstance(progress, str) else None
    return tqdm(total=n, unit="row", desc=desc, disable=not progress)


def _run_local(fn, shared, batched, n: int, chunk: int, progress=None, min_rows=SMALL_BATCH):
    """All rows of `batched` (numpy leaves, n rows) on this process's devices, in chunks."""
    mesh = batch_mesh()
    n_dev = 1 if mesh is None else mesh.size
    size = chunk_rows(n, chunk, n_dev, min_rows)
    if size >= LARGE_BATCH and _in_pieces():
        with _progress_bar(n, progress) as bar:
            return _Part(fn, shared, batched, chunk, min_rows, cpu_workers()).result(bar)
    if mesh is not None:
        rows = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
        everywhere = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
        shared = jax.tree.map(
            lambda x: jax.device_put(x, everywhere) if eqx.is_array(x) else x, shared
        )

    def launch(start):
        part = _pad_rows(_slice_rows(batched, start, start + size), size)
        if mesh is not None:
            part = jax.device_put(part, rows)
        return _vmapped_for(size)(fn, shared, part)

    starts = range(0, n, size)
    if len(starts) == 1 and n == size and mesh is None:
        return launch(0)  # one chunk on one device: keep the device arrays
    out = None
    pending = None
    with _progress_bar(n, progress) as bar:
        for start in list(starts) + [None]:
            nxt = None if start is None else (start, launch(start))
            if pending is not None:
                p_start, p_out = pending
                m = min(size, n - p_start)
                leaves, treedef = jax.tree.flatten(p_out)
                if out is None:
                    out = [np.empty((n,) + x.shape[1:], dtype=x.dtype) for x in leaves]
                for o, x in zip(out, leaves):
                    o[p_start : p_start + m] = np.asarray(x)[:m]
                bar.update(m)
            pending = nxt
    return jax.tree.unflatten(treedef, out)


def run_batch(
    fn, shared, batched, *, chunk: int = DEFAULT_CHUNK, progress=None, min_rows=SMALL_BATCH
):
    """`jax.vmap(lambda row: fn(shared, row))(batched)`, chunked and spread over devices and
    processes (see the module docstring).

    `fn(shared, row)`: a module-level function for ONE row (a stable identity, so it compiles
    once per shape); `shared`: a pytree used by every row (tables, effects, options; non-array
    leaves are static); `batched`: a pytree whose array leaves all have the same leading
    number of rows. Returns the pytree of outputs with that leading axis: jax arrays when the
    input was traced, or filled one chunk exactly (`chunk_rows`) on one device and is not a
    large batch on the CPU (which runs in per-core pieces), else numpy arrays.
    `progress`: a description string (or True) for a progress bar over the rows.
    `min_rows`: the fewest rows of a compiled small batch (`chunk_rows`); lower it where a
    row is costly (a Monte Carlo row is a forward solve of every pose).
    """
    if not is_concrete(shared, batched):
        return _chunked(fn, shared, batched, chunk)
    batched = jax.tree.map(np.asarray, batched)
    n = jax.tree.leaves(batched)[0].shape[0]
    if n == 0:
        return _vmapped_quick(fn, shared, batched)
    n_proc = jax.process_count()
    if n_proc == 1:
        return _run_local(fn, shared, batched, n, chunk, progress, min_rows)
    from jax.experimental import multihost_utils

    per = math.ceil(n / n_proc)
    start = jax.process_index() * per
    mine = _pad_rows(_slice_rows(batched, min(start, n - 1), min(start + per, n)), per)
    local = _run_local(fn, shared, mine, per, chunk, progress, min_rows)
    local = jax.tree.map(np.asarray, local)
    gathered = multihost_utils.process_allgather(local, tiled=True)
    return jax.tree.map(lambda x: np.asarray(x)[:n], gathered)
