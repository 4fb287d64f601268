"""Where the test suite's time goes to compilation: a pytest plugin and its summary.

    python -m pytest -p benchmarks.compile_profile          # writes one JSON per worker
    python -m benchmarks.compile_profile                     # prints the summary

The plugin sums JAX's compile events (`jax.monitoring`: tracing, lowering, XLA's backend
compile) per test and per program name, in each pytest-xdist worker, and writes them to
`$JAXTABLE_COMPILE_PROFILE` (default `.pytest_cache/compile_profile`). Run it from an empty
compilation cache (`rm -rf .pytest_cache`) to see what a clean clone compiles. Programs named
`jit(<operation>)` for a single jax.numpy / lax operation come from code run eagerly, op by
op. Tests that start subprocesses (studies, scale-out workers, the command line's child
runs) compile outside these sums.
"""

import collections
import functools
import json
import os
import re
import sys
import time
from pathlib import Path

import pytest

DEFAULT = Path(".pytest_cache") / "compile_profile"
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}


def _out() -> Path:
    return Path(os.environ.get("JAXTABLE_COMPILE_PROFILE", DEFAULT))


class _Recorder:
    def __init__(self):
        self.test = "<outside tests>"
        self.tests = collections.defaultdict(lambda: collections.Counter())
        self.programs = collections.defaultdict(lambda: collections.Counter())
        self.wall = {}
        self.span = {}  # test -> (start, end), seconds since the epoch

    def listen(self, event, duration, fun_name="?", **_):
        kind = EVENTS.get(event)
        if kind is None:
            return
        self.tests[self.test][kind] += duration
        self.tests[self.test][kind + "_n"] += 1
        self.programs[fun_name][kind] += duration
        if kind == "compile":
            self.programs[fun_name]["n"] += 1

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        self.test = item.nodeid
        t0, e0 = time.perf_counter(), time.time()
        yield
        self.wall[item.nodeid] = time.perf_counter() - t0
        self.span[item.nodeid] = (e0, time.time())
        self.test = "<between tests>"

    def pytest_unconfigure(self, config):
        out = _out()
        out.mkdir(parents=True, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        data = {
            "tests": self.tests,
            "programs": self.programs,
            "wall": self.wall,
            "span": self.span,
            "worker": worker,
        }
        (out / f"{worker}.json").write_text(json.dumps(data))


def pytest_configure(config):
    import jax.monitoring

    rec = _Recorder()
    jax.monitoring.register_event_duration_secs_listener(rec.listen)
    config.pluginmanager.register(rec, "compile_profile_recorder")


@functools.cache
def _library_functions() -> frozenset:
    """Names of jaxtable's module-level functions: a program named after one is jaxtable's
    own (the design optimiser's `_round`), not numpy's function of that name run eagerly."""
    import jaxtable

    root = Path(jaxtable.__file__).parent
    return frozenset(
        m for f in root.rglob("*.py") for m in re.findall(r"^def (\w+)\(", f.read_text(), re.M)
    )


def is_eager_operation(name: str) -> bool:
    """Whether a program's name ("jit(add)") is a single jax.numpy / lax operation run
    eagerly, op by op, rather than a compiled function."""
    import jax.lax
    import jax.numpy as jnp

    m = re.fullmatch(r"jit\(([a-z_0-9]+)\)", name)
    if not m or m.group(1) in _library_functions():
        return False
    return hasattr(jnp, m.group(1).lstrip("_")) or hasattr(jax.lax, m.group(1))


def summary(out: Path, top: int = 25) -> str:
    tests, programs, wall = {}, collections.defaultdict(collections.Counter), {}
    spans = {}  # worker -> (first test's start, last test's end)
    for path in sorted(out.glob("*.json")):
        d = json.loads(path.read_text())
        tests.update(d["tests"])
        wall.update(d["wall"])
        ends = list(d.get("span", {}).values())
        if ends:
            spans[d.get("worker", path.stem)] = (min(e[0] for e in ends), max(e[1] for e in ends))
        for k, v in d["programs"].items():
            programs[k].update(v)
    total = collections.Counter()
    for v in tests.values():
        total.update(v)
    eager = [v for k, v in programs.items() if is_eager_operation(k)]
    lines = [
        f"{len(wall)} tests, {sum(wall.values()):.0f} worker-s in tests; XLA compile "
        f"{total['compile']:.0f} s ({total['compile_n']:.0f} programs), tracing "
        f"{total['trace']:.0f} s, lowering {total['lower']:.0f} s; eager single operations "
        f"{sum(v['compile'] for v in eager):.0f} s ({sum(v['n'] for v in eager):.0f} programs)",
        "",
        "programs by compile time (s, count):",
    ]
    for k, v in sorted(programs.items(), key=lambda kv: -kv[1]["compile"])[:top]:
        lines.append(f"  {v['compile']:8.1f} {v['n']:6.0f}  {k}")
    lines += ["", "programs by tracing time (s; outermost traces only):"]
    for k, v in sorted(programs.items(), key=lambda kv: -kv[1]["trace"])[:top]:
        lines.append(f"  {v['trace']:8.1f}  {k}")
    if spans:
        t0, t1 = min(a for a, _ in spans.values()), max(b for _, b in spans.values())
        lines += ["", f"workers (s from the first test's start; the last ends at {t1 - t0:.0f}):"]
        for w, (a, b) in sorted(spans.items()):
            lines.append(f"  {w}: first test {a - t0:6.1f}, last ends {b - t0:6.1f}")
    lines += ["", "tests by wall time (s; compile, trace, compiled programs):"]
    for t in sorted(wall, key=wall.get, reverse=True)[:top]:
        v = tests.get(t, {})
        lines.append(
            f"  {wall[t]:6.1f}  {v.get('compile', 0):6.1f} {v.get('trace', 0):5.1f} "
            f"{v.get('compile_n', 0):5.0f}  {t}"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    print(summary(Path(sys.argv[1]) if len(sys.argv) > 1 else _out()))
