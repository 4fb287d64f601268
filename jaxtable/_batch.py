"""Batching: apply a one-pose function over any leading dims, in bounded-memory chunks."""

import jax
import jax.numpy as jnp

DEFAULT_CHUNK = 1 << 16


def map_batch(fn, *xs, chunk: int = DEFAULT_CHUNK):
    """`jax.vmap(fn)(*xs)` over the leading axis of every x, in chunks of `chunk` rows.

    Up to `chunk` rows: one vmap. Beyond: `jax.lax.map` with `batch_size=chunk`, so peak
    memory is that of one chunk whatever the batch size.
    """
    n = xs[0].shape[0]
    if n <= chunk:
        return jax.vmap(fn)(*xs)
    return jax.lax.map(lambda a: fn(*a), xs, batch_size=chunk)


def flatten_batch(x, tail: int):
    """Reshape (..., *tail_shape) -> (N, *tail_shape); returns (flat, batch_shape)."""
    x = jnp.asarray(x, dtype=jnp.float64)
    batch_shape = x.shape[: x.ndim - tail]
    return x.reshape((-1,) + x.shape[x.ndim - tail :]), batch_shape
