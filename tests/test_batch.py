"""Chunked batch runner, the real-time single-pose command and streamed command maps."""

import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import compiled_programs, random_poses

import jaxtable as jt
from jaxtable._batch import run_batch


def _row(shared, row):
    scale, offset = shared
    x, y = row
    return scale * jnp.sin(x) + offset, jnp.sum(y * y)


def test_run_batch_chunks_pad_and_trace_give_the_plain_vmap():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(23, 3))
    y = rng.normal(size=(23, 2))
    shared = (jnp.asarray(2.0), jnp.asarray([1.0, 2.0, 3.0]))
    want = jax.vmap(lambda r: _row(shared, r))((x, y))
    for chunk in (1, 5, 23, 64):  # 23 = 4 chunks of 5 + a padded one
        got = run_batch(_row, shared, (x, y), chunk=chunk)
        for g, w in zip(got, want):
            np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-15)
    # traced input (inside jit): lax.map over chunks, same numbers
    got = jax.jit(lambda a, b: run_batch(_row, shared, (a, b), chunk=5))(x, y)
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(want[0]), rtol=1e-15)


def test_small_batches_share_a_compiled_size_and_lose_no_row():
    """Single-chunk batches are padded to a power of two (at least SMALL_BATCH = 256 rows or
    a caller's `min_rows`, at most the chunk) under LARGE_BATCH rows, to a multiple of
    chunk/16 above; several chunks are equal multiples of chunk/16. Sizes by hand; 1, 150
    and 200 rows then run one compiled program, every row equal to the plain vmap."""

    from jaxtable._batch import SMALL_BATCH, chunk_rows

    assert SMALL_BATCH == 256
    sizes = (1, 8, 9, 150, 200, 256, 257, 4095)
    assert [chunk_rows(n, 1 << 16) for n in sizes] == [256] * 6 + [512, 4096]
    assert [chunk_rows(n, 1 << 16, min_rows=8) for n in sizes] == [
        8,
        8,
        16,
        256,
        256,
        256,
        512,
        4096,
    ]
    assert chunk_rows(5, 5) == 5 and chunk_rows(3, 6) == 6  # never above the chunk
    assert chunk_rows(5000, 1 << 16) == 8192 and chunk_rows(4096, 1 << 16) == 4096
    assert chunk_rows(100_000, 1 << 16) == 53248  # 2 chunks of 50000 -> 13 x 4096
    assert chunk_rows(23, 5) == 5 and chunk_rows(150, 200, n_dev=4) == 200
    assert chunk_rows(3, 6, n_dev=4) == 8  # a multiple of the device count
    assert chunk_rows(3, 1 << 16, n_dev=3, min_rows=8) == 9

    def odd(shared, row):  # a function no other test batches: its compiles are this test's
        return jnp.cos(row) * shared

    with compiled_programs() as compiles:
        for n in (1, 150, 200):
            x = np.random.default_rng(n).normal(size=(n, 3))
            got = np.asarray(run_batch(odd, jnp.asarray(1.5), x))
            assert got.shape == (n, 3)
            np.testing.assert_allclose(got, np.cos(x) * 1.5, rtol=1e-14, atol=1e-15)
    assert compiles.count("jit(_vmap)") == 1, compiles


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="per-core pieces are the CPU's")
def test_large_batches_run_in_per_core_pieces_and_lose_no_row(monkeypatch):
    """A large batch on the CPU runs as pieces of BLOCK-row blocks from host threads: the
    piece sizes by hand, and every row equal to numpy's value of the row function, for
    several chunks, a padded last piece, one worker or several, an empty batch; an error
    raised inside a piece reaches the caller; `stream_batch` yields every part, small and
    large, in order."""
    import equinox as eqx

    from jaxtable import _batch
    from jaxtable._batch import BLOCK, LARGE_BATCH, piece_rows, stream_batch

    assert BLOCK == 128 and LARGE_BATCH == 4096
    # the rows a worker gets, rounded up to m·2^k (m = 4..7) and to BLOCK rows, at most the
    # largest power of two ≤ chunk / workers
    assert piece_rows(10**6, 1 << 16, 2) == 32768  # 500,000 a worker: capped at 2¹⁵
    assert piece_rows(10**4, 1 << 15, 2) == 5120  # 5000 -> 5·2¹⁰
    assert piece_rows(4106, 1 << 20, 2) == 2560  # 2053 -> 5·2⁹
    assert piece_rows(4096, 1 << 16, 14) == 384  # 293 -> 5·2⁶ = 320 -> 3 blocks
    assert piece_rows(10**6, 1 << 13, 16) == 512  # capped at 8192 / 16
    assert piece_rows(12345, 1 << 16, 1) == 14336  # 7·2¹¹
    rng = np.random.default_rng(7)
    shared = (jnp.asarray(2.0), jnp.asarray([1.0, 2.0, 3.0]))
    for workers in (1, 3):
        monkeypatch.setattr(_batch, "cpu_workers", lambda w=workers: w)
        for n in (LARGE_BATCH, 3 * LARGE_BATCH + 37):
            x, y = rng.normal(size=(n, 3)), rng.normal(size=(n, 2))
            a, b = run_batch(_row, shared, (x, y), chunk=LARGE_BATCH)
            assert isinstance(a, np.ndarray) and a.shape == (n, 3) and b.shape == (n,)
            np.testing.assert_allclose(a, 2.0 * np.sin(x) + [1.0, 2.0, 3.0], rtol=1e-14)
            np.testing.assert_allclose(b, (y * y).sum(1), rtol=1e-14)
    a, b = run_batch(_row, shared, (np.zeros((0, 3)), np.zeros((0, 2))))
    assert a.shape == (0, 3) and b.shape == (0,)

    def picky(shared, row):
        return eqx.error_if(row, row[0] > 100.0, "row too large")

    x = np.zeros((2 * LARGE_BATCH, 3))
    x[LARGE_BATCH + 5, 0] = 1e3  # in the second piece
    with pytest.raises(Exception, match="row too large"):
        run_batch(picky, None, x)
    # one worker, 16 pieces: the error in the second stops the pieces not yet started. The
    # worker waits at the start of a chosen piece until the test releases it (after the
    # call returned), so the count does not depend on how the threads are scheduled
    monkeypatch.setattr(_batch, "cpu_workers", lambda: 1)
    calls, real, release, gate = [], _batch._blocked, threading.Event(), {"at": 3}

    def counted(*args):
        calls.append(1)
        if len(calls) == gate["at"]:
            release.wait(60)
        return real(*args)

    monkeypatch.setattr(_batch, "_blocked", counted)
    x = np.zeros((16 * LARGE_BATCH, 3))
    x[LARGE_BATCH + 5, 0] = 1e3
    with pytest.raises(Exception, match="row too large"):
        run_batch(picky, None, x, chunk=LARGE_BATCH)
    release.set()
    _batch._pool(1).submit(lambda: None).result()  # the pool drained of whatever still ran
    assert len(calls) in (2, 3), len(calls)  # 16 with the rest left running
    # a stream the caller leaves after its first part: the part computed ahead is dropped
    calls.clear()
    release.clear()
    gate["at"] = 17  # the second part's first piece
    stream = stream_batch(_row, shared, ((x, x[:, :2]) for _ in range(8)), chunk=LARGE_BATCH)
    next(stream)
    stream.close()
    release.set()
    _batch._pool(1).submit(lambda: None).result()
    assert len(calls) in (16, 17), len(calls)  # 32 with the second part left running
    monkeypatch.setattr(_batch, "_blocked", real)

    sizes = [5000, 100, 2 * LARGE_BATCH, 0, 7]
    parts = [rng.normal(size=(n, 3)) for n in sizes]
    seen = list(stream_batch(lambda s, r: jnp.cos(r) * s, 1.5, iter(parts), chunk=LARGE_BATCH))
    assert [len(p) for p, _ in seen] == sizes
    for (p, got), want in zip(seen, parts):
        assert p is want
        np.testing.assert_allclose(got, np.cos(want) * 1.5, rtol=1e-14)


def test_actuator_command_chunked_equals_one_chunk(table):
    poses = random_poses(1000, seed=3)
    a = np.asarray(jt.actuator_command(table, poses))
    b = np.asarray(jt.actuator_command(table, poses, chunk=96))
    np.testing.assert_array_equal(a, b)
    # and against the definition: rigid length minus the spiral extension
    want = np.asarray(jt.leg_lengths(table, poses) - jt.spiral_extension(table, poses))
    np.testing.assert_allclose(a, want, atol=1e-9)


def test_command_function_matches_batch_command_and_checks_input(table):
    poses = random_poses(50, seed=4)
    f = jt.command_function(table)
    got = np.stack([f(q) for q in poses])
    np.testing.assert_allclose(got, np.asarray(jt.actuator_command(table, poses)), atol=1e-12)
    rigid = jt.command_function(table, compensated=False)
    np.testing.assert_allclose(rigid(poses[0]), np.asarray(jt.leg_lengths(table, poses[0])))
    assert isinstance(got[0], np.ndarray) and got[0].dtype == np.float64
    with pytest.raises(jt.KinematicsError, match="non-finite"):
        f([0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        f(np.zeros(5))
    with pytest.raises(jt.KinematicsError, match="outside the stroke"):
        f([0, 0, 900.0, 0, 0, 0])


def test_command_map_summary_matches_direct_evaluation(table):
    grid = jt.workspace_slice(("x", "roll"), n=(9, 7))
    poses = grid.poses()
    cmd = np.asarray(jt.actuator_command(table, poses))
    spiral = np.abs(np.asarray(jt.spiral_extension(table, poses)))
    reach = np.asarray(jt.reachable(table, poses))
    assert reach.any()
    # 7 chunks, last one short, computed ahead on the pool's threads (`stream_batch`): the
    # new program is traced and compiled once, not once per thread that first meets it
    # (the traced-program cache, `_tracecache`, is on in the tests; no other test maps
    # chunks of 10 with this kernel)
    with compiled_programs() as compiles:
        m, s = jt.command_map(table, grid, keep=True, chunk=10)
    assert compiles.count("jit(_vmap__command_map_row)") == 1, compiles
    assert s["poses"] == 63 and s["reachable"] == int(reach.sum())
    np.testing.assert_allclose(s["command_min_mm"], cmd[reach].min(0), atol=1e-9)
    np.testing.assert_allclose(s["command_max_mm"], cmd[reach].max(0), atol=1e-9)
    np.testing.assert_allclose(s["spiral_max_mm"], spiral[reach].max(0), atol=1e-12)
    k = np.argmax(np.where(reach, spiral.max(1), -1))
    np.testing.assert_allclose(s["spiral_worst_pose"], poses[k])
    assert m.command.shape == (9, 7, 6)
    np.testing.assert_allclose(m.command.reshape(-1, 6), cmd, rtol=1e-6)
    np.testing.assert_array_equal(m.reachable.reshape(-1), reach)
