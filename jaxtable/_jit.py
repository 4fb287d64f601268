"""How jaxtable compiles its programs: quick compilation where compile time is the wait.

Most of jaxtable's programs run once or a few times per call on small data: a fit and its
Jacobian, a diagnosis's fits, a design optimisation, pose selection, the batch kernels of a
few hundred rows that simulate, calibrate and validate. What the user waits for there is
XLA's compilation. XLA's CPU backend compiles them faster with its classic loop emitters
(`xla_cpu_use_fusion_emitters=False`) than with the fusion emitters it uses by default, and
runs them as fast: the 54-parameter calibration's fit program 3.7 → 2.4 s, a forward
solve's batch kernel 4.0 → 2.4 s, the default test suite on a clean clone 14–15 → 12 min.
The kernels that stream large batches (`_batch.run_batch` chunks of `LARGE_BATCH` rows or
more: error maps, command maps, forward kinematics of many poses) keep XLA's default: they
run many times, and the default runs the error map's kernel ~14 % faster.

`jit(fun)`: `eqx.filter_jit` with `compiler_options()`. The options are checked once, on
first use, by compiling a no-op with them: a backend or jaxlib that does not know them gets
XLA's defaults. `$JAXTABLE_QUICK_COMPILE=0` gives XLA's defaults everywhere (any other value
than 0 or 1 raises a ValueError naming the variable). Inside another traced function (a
user's `jax.jit`, `vmap` or `grad` around a jaxtable call) the outermost program's options
apply: JAX refuses compiler options on a nested `jit`.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax._src import core as jax_core  # trace_state_clean: is any trace under way

from . import _tracecache
from ._errors import env_switch, is_concrete

ENV = "JAXTABLE_QUICK_COMPILE"
QUICK = {"xla_cpu_use_fusion_emitters": False}
LARGE_BATCH = 4096  # rows from which a batch kernel keeps XLA's default emitters


def quick_compile_requested() -> bool:
    """Whether `$JAXTABLE_QUICK_COMPILE` asks for quick compilation (default yes)."""
    return env_switch(ENV, "XLA's defaults", "quick compile")


@functools.cache
def _supported() -> bool:
    try:
        jax.jit(lambda x: x + 1, compiler_options=QUICK).lower(1.0).compile()
    except Exception:  # an unknown option is an error of the compile step
        return False
    return True


def compiler_options() -> dict:
    """The options `jit` compiles with: `QUICK` unless turned off or unsupported, else {}."""
    return dict(QUICK) if quick_compile_requested() and _supported() else {}


def _inside_a_trace(args, kwargs) -> bool:
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((args, kwargs))):
        return True
    clean = getattr(jax_core, "trace_state_clean", None)
    return clean is not None and not clean()


def jit(fun):
    """`eqx.filter_jit(fun)` compiled with `compiler_options()`, decided at each top-level
    call (so `$JAXTABLE_QUICK_COMPILE` may change between calls); at the top level through
    the traced programs stored beside the compilation cache where it is on
    (`_tracecache.call`). Called inside another traced function it is a plain
    `eqx.filter_jit` (JAX accepts compiler options on the outermost program only)."""
    compiled = {}

    def get(options: dict):
        key = tuple(sorted(options.items()))
        if key not in compiled:
            kw = {"compiler_options": options} if options else {}
            compiled[key] = eqx.filter_jit(fun, **kw)
        return compiled[key]

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if _inside_a_trace(args, kwargs):
            return get({})(*args, **kwargs)
        options = compiler_options()
        return _tracecache.call(fun, options, args, kwargs, lambda: get(options)(*args, **kwargs))

    return call


def device_array(x, shape=None, dtype=None):
    """`jnp.asarray(x, dtype)` (reshaped to `shape`, if given) without an eager program where
    `x` is concrete: numpy converts and reshapes it and `jax.device_put` copies it to the
    device, uncommitted, as `jnp.asarray` places it. Eagerly, `jnp.asarray` of a numpy array
    (`jit(stage)`), a reshape, a dtype conversion or a broadcast each compile a program per
    shape and dtype: ~20 ms from an empty cache, and every batch size is a new shape. A
    traced `x` (or a pytree holding tracers) goes through jnp."""
    if not is_concrete(x):
        x = jnp.asarray(x, dtype=dtype)
        return x if shape is None else x.reshape(shape)
    if (
        isinstance(x, jax.Array)
        and (shape is None or x.shape == tuple(shape))
        and (dtype is None or x.dtype == np.dtype(dtype))
    ):
        return x
    x = np.asarray(x, dtype=dtype)
    return jax.device_put(x if shape is None else x.reshape(shape))
