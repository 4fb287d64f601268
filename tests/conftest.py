import contextlib
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "jaxtable"
# a module that imports jaxtyping or writes an array annotation (`Float[Array, "n 6"]`), or
# defines custom derivatives: beartype.claw's decorator would wrap a `jax.custom_jvp` before
# its `defjvp` (jaxtyping's goes to the bottom of a function's decorators)
_ARRAY_ANNOTATIONS = re.compile(
    r"jaxtyping|custom_jvp|custom_vjp|\b(Float|Int|Bool|Shaped|Real|Num|Key)\["
)


def annotation_checks() -> tuple[list, list]:
    """(modules checked by jaxtyping, modules checked by beartype alone): every module of
    jaxtable, by whether it has array annotations (`_ARRAY_ANNOTATIONS`)."""
    by_jaxtyping, by_beartype = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        shaped = _ARRAY_ANNOTATIONS.search(path.read_text(encoding="utf-8"))
        (by_jaxtyping if shaped else by_beartype).append(name)
    return by_jaxtyping, by_beartype


def _check_annotations() -> None:
    """Every annotation in jaxtable checked at call time, installed before jaxtable is
    imported. Modules with array annotations: jaxtyping's import hook
    (`@jaxtyped(typechecker=beartype)` on every function and dataclass: array shapes, and
    named dimensions agreeing across a call's arguments and result). The other modules:
    beartype's own import hook (`beartype.claw`: every annotated function, dataclass field
    and annotated assignment). Their annotations are plain types, which `@jaxtyped` would
    check with beartype just the same, at 5-12 µs more a call (argument binding and the
    dimension memo, for nothing there): with jaxtyping's hook on every module, test_structure,
    test_diagnose and test_design took 186 s from an empty cache and 96-99 s warm on two
    workers, with this split 169 and 90-92 (benchmarks/NOTES.md)."""
    from beartype import BeartypeConf
    from beartype.claw import beartype_packages
    from jaxtyping import TypeCheckError, install_import_hook

    if "jaxtable" in sys.modules:
        raise RuntimeError("jaxtable was imported before its annotation checks were installed")
    by_jaxtyping, by_beartype = annotation_checks()
    install_import_hook(by_jaxtyping, "beartype.beartype")
    # by name, not the package: beartype.claw's hook on "jaxtable" would reach every
    # submodule (jaxtable/__init__.py defines no function: it only imports). Violations
    # raise jaxtyping's TypeCheckError (a TypeError) under both hooks.
    beartype_packages(
        [m for m in by_beartype if m != "jaxtable"],
        conf=BeartypeConf(violation_type=TypeCheckError),
    )


_check_annotations()

# Share compiled programs between the test workers (pytest-xdist) and between runs: JAX's
# persistent compilation cache, in the (git-ignored) pytest cache directory.
# The command line (main() called in tests) turns the cache on where JAXTABLE_CACHE_DIR says.
# JAXTABLE_TEST_CACHE moves it (the benchmark times the suite from an empty one).
CACHE = Path(
    os.environ.get("JAXTABLE_TEST_CACHE")
    or Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax"
)
os.environ["JAXTABLE_CACHE_DIR"] = str(CACHE)

# the checkout's benchmarks/ importable (the compile profile's `is_eager_operation`, the
# baselines), however pytest was started
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# BLAS pools at one thread in the test workers: two workers share two cores, and many tests
# call internal fitting code that jaxtable's public functions would otherwise run at one
# thread (jaxtable/_threads.py; with two-thread pools the suite took 2.4x as long). The
# environment carries it to the subprocesses (studies, the command line, scale-out workers).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def _hands_out_tests_only(config) -> bool:
    """Whether this process is pytest-xdist's controller, which hands the tests to the
    workers and runs none of them."""
    if hasattr(config, "workerinput"):
        return False
    try:
        workers = config.getoption("numprocesses")
    except ValueError:  # xdist not loaded
        return False
    return bool(workers) and not config.getoption("collectonly")


def pytest_configure(config):
    """float64, the compilation cache and one-thread BLAS pools in every process that runs
    tests. Not in xdist's controller: importing jaxtable there (~4 s with the annotation
    checks' instrumentation) would only delay the workers' start."""
    if _hands_out_tests_only(config):
        return
    import jax
    from threadpoolctl import threadpool_limits

    jax.config.update("jax_enable_x64", True)
    import jaxtable as jt

    # the library's own rule (jaxtable/_cache.py): every program stored, and a size limit,
    # which makes JAX lock the directory around every read and write (a worker could
    # otherwise read an entry the other is still writing and crash)
    jt.enable_compilation_cache(CACHE)
    threadpool_limits(limits=1, user_api="blas")


# Workspace box used by the tests (mm, rad): the reference table's combined-motion box.
BOX = np.array([100.0, 100.0, 50.0, np.deg2rad(7.5), np.deg2rad(7.5), np.deg2rad(10.0)])


def quick_jit(fun, **kw):
    """`jax.jit` compiling with the options jaxtable compiles its own programs with
    (`_jit.compiler_options`, XLA's classic CPU emitters): a test's jitted check of a large
    program compiles as quickly as the library's programs do."""
    import jax

    from jaxtable._jit import compiler_options

    return jax.jit(fun, compiler_options=compiler_options(), **kw)


@contextlib.contextmanager
def compiled_programs(stage: str = "backend_compile"):
    """The names of the programs compiled (or read from the persistent cache) inside the
    `with` block, as JAX's compile events report them, e.g. "jit(_vmap__design_row)".
    `stage="jaxpr_to_mlir_module"`: the programs lowered, i.e. every program this process
    had not run at those shapes before, whether XLA then compiles it or the persistent
    cache holds it."""
    import jax.monitoring

    names = []

    def listen(event, duration, fun_name="?", **_):
        if event == f"/jax/core/compile/{stage}_duration":
            names.append(fun_name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


# Modules of short tests (each well under a second or two) run last. The workers share the
# tests by work stealing (`--dist worksteal` in pyproject's addopts: each starts on one
# contiguous half of the collection and, when its queue runs out, takes half of what the
# other has left), so the last tests either worker runs are short ones and both end
# together. With xdist's default `load` scheduling, which hands out runs of consecutive
# tests as large as half a worker's share, one worker ran the studies and the tolerance
# checks while the other had finished: one core idle for the last 35 s of a profiled clean
# run, 4 s with work stealing (benchmarks/NOTES.md).
LAST = (
    "test_batch.py",
    "test_cache.py",
    "test_effects.py",
    "test_params.py",
    "test_reference_table.py",
    "test_rotation.py",
    "test_table_io.py",
    "test_threads.py",
    "test_tracecache.py",
)


def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: item.path.name in LAST)  # stable: the rest in name order


@pytest.fixture(scope="session")
def table():
    import jaxtable as jt

    return jt.reference_table()


def random_poses(n, seed=0, box=BOX):
    return np.random.default_rng(seed).uniform(-1, 1, (n, 6)) * box


def x_line(xs):
    p = np.zeros((len(xs), 6))
    p[:, 0] = xs
    return p
