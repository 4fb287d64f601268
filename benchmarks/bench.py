"""Benchmarks with baselines measured in the same run (`python -m benchmarks`, `jaxtable bench`,
studies/benchmark.py).

Every throughput is the median of repeated runs after a first (compiling) call; the compile
time is reported separately (first call minus the median). Baselines, written as a user
would write them:
- inverse kinematics + spiral term in vectorised numpy ((N, 6, 3) arrays, the twist from the
  cross products m = n×u, k = j×u as in the paper);
- forward kinematics with `scipy.optimize.fsolve`, pose by pose, on that numpy model;
- the tolerance error map in vectorised numpy: the pose Jacobian and the joints' gains by
  central differences of that model, `np.linalg.inv` and `np.linalg.cond` over the poses;
- the design criteria in a numpy loop over designs.

The machine limit of the inverse kinematics is estimated from the compiled kernel: its
operations per pose (counted in the optimised HLO: arithmetic, sqrt, sin/cos, atan2) times
each operation's throughput, measured here on large arrays over all cores.
"""

import functools
import json
import math
import os
import platform
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtable import (
    GEOMETRY,
    LeadScale,
    Spiral,
    Table,
    Tolerances,
    actuator_command,
    command_function,
    error_map,
    fit,
    forward_solve,
    perturb_table,
    plan_random,
    pose_sensitivity,
    posterior,
    setup,
    simulate,
    tracker6,
)

# the compiled kernel itself (op counts, machine limit) is an internal on purpose
from jaxtable._analysis.errormap import _budget_row
from jaxtable._context import Context
from jaxtable._effects import resolve_effects
from jaxtable._forward import platform_radius
from jaxtable._model import inverse_extension

from .baselines import numpy_command, numpy_design_criteria, numpy_error_map, scipy_forward

CYCLE_US = 1000.0  # the real-time budget assumed: a 1 kHz servo cycle
BOX = np.array([100.0, 100.0, 50.0, np.deg2rad(7.5), np.deg2rad(7.5), np.deg2rad(10.0)])


def _poses(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (n, 6)) * BOX


def _timed(fn, reps: int):
    """(first-call seconds, median seconds of `reps` further calls)."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return first, float(np.median(ts))


def _latencies(fn, poses: np.ndarray, warmup: int = 200) -> np.ndarray:
    """Seconds of each call fn(pose), one pose at a time, after `warmup` untimed calls."""
    for p in poses[:warmup]:
        fn(p)
    out = np.empty(len(poses))
    clock = time.perf_counter
    for i, p in enumerate(poses):
        t0 = clock()
        fn(p)
        out[i] = clock() - t0
    return out


def _ready(x):
    return jax.block_until_ready(x)


# ---------------------------------------------------------------- machine limit


def _op_rates(n: int = 1 << 22, reps: int = 5) -> dict:
    """Elements per second of float64 ops, all cores (jit, XLA CPU). Each kernel applies its
    op `depth` times to every element, independently (a sum of op(x + c_k)), so the figure
    is compute throughput with instruction-level parallelism, as inside the kinematics
    kernel, not memory bandwidth or one op's latency."""
    x = jnp.asarray(np.random.default_rng(0).uniform(0.1, 1.0, n))
    depth = 16
    c = [0.5 + 0.01 * k for k in range(depth)]

    def indep(op):
        return jax.jit(lambda a: sum(op(a + ck) for ck in c))

    def fma_chain(a):  # two dependent ops a step, but 64 steps over vectorised lanes
        for _ in range(4 * depth):
            a = a * 0.999 + 0.001
        return a

    kernels = {
        "arith": (jax.jit(fma_chain), 8 * depth),
        "divide": (indep(lambda a: 1.0 / a), depth),
        "sqrt": (indep(jnp.sqrt), depth),
        "sin": (indep(jnp.sin), depth),
        "cos": (indep(jnp.cos), depth),
        "atan2": (indep(lambda a: jnp.arctan2(a, 0.7)), depth),
    }
    rates = {}
    for name, (f, ops) in kernels.items():
        _, t = _timed(lambda f=f: _ready(f(x)), reps)
        rates[name] = n * ops / t
    return rates


_ARITH = (
    "add",
    "subtract",
    "multiply",
    "negate",
    "maximum",
    "minimum",
    "select",
    "compare",
    "abs",
    "and",
    "or",
    "clamp",
)
# the few other transcendental ops (power, log, tan in the error map) are priced as a sine
_OPS = {
    "sqrt": ("sqrt",),
    "sin": ("sine", "power", "log", "exponential", "tan"),
    "cos": ("cosine",),
    "atan2": ("atan2",),
}
_INSTR = re.compile(
    r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*\w+\[([\d,]*)\][^ ]*\s+([a-z0-9\-]+)\((.*)$"
)


_COMPUTATION = re.compile(r"^\s*(?:ENTRY\s+)?%?([\w.\-]+)\s*\(")
_CALLS = re.compile(r"\b(calls|body|condition|to_apply)=%?([\w.\-]+)")
_TRIPS = re.compile(r'"known_trip_count":\{"n":"(\d+)"\}')


def hlo_op_counts(text: str, batch: int) -> dict:
    """Operations per pose of a compiled program batched over `batch` poses, from its optimised
    HLO text: an element-wise op counts its output elements divided by the batch size (an op
    on (N, 6) is 6 per pose, on (N,) is 1); a reduction counts its input elements less its
    output's, a dot two per multiply-add. Ops without the batch as leading dimension are
    per-table constants, evaluated once per batch, and not counted. Each computation counts
    as often as it runs: a `while` loop's body times its known trip count (XLA's
    `known_trip_count`; a loop without one counts once), its condition once more than that."""
    own = {}  # computation -> its own counts
    callees = {}  # computation -> [(called computation, times)]
    entry = None
    shapes = {}  # instruction name -> dims, within the current computation
    comp = None
    for line in text.splitlines():
        if line.rstrip().endswith("{"):  # a computation starts: names are local to it
            m = _COMPUTATION.search(line)
            comp = m.group(1) if m else line
            if line.lstrip().startswith("ENTRY"):
                entry = comp
            own[comp] = dict.fromkeys(("arith", "sqrt", "sin", "cos", "atan2", "divide"), 0.0)
            callees[comp] = []
            shapes = {}
            continue
        if comp is None:
            continue
        # calls from any instruction, tuple-shaped ones (loops, multi-output fusions) too
        trips = _TRIPS.search(line) if " while(" in line else None
        n = int(trips.group(1)) if trips else 1
        for kind, callee in _CALLS.findall(line):
            times = {"body": n, "condition": n + 1 if trips else 1}.get(kind, 1)
            callees[comp].append((callee, times))
        m = _INSTR.search(line)
        if not m:
            continue
        name, dims, op, rest = (
            m.group(1),
            [int(d) for d in m.group(2).split(",") if d],
            *m.groups()[2:],
        )
        shapes[name] = dims
        if not dims or dims[0] != batch:
            continue  # per-table constants, evaluated once per batch
        out = math.prod(dims[1:])
        counts = own[comp]
        if op in _ARITH:
            counts["arith"] += out
        elif op == "divide":
            counts["divide"] += out
        elif op in ("reduce", "dot"):
            operands = re.findall(r"%([\w.\-]+)", rest.split(")")[0])
            first = shapes.get(operands[0]) if operands else None
            if not first or first[0] != batch:
                continue
            if op == "reduce":
                counts["arith"] += math.prod(first[1:]) - out
            else:
                k = re.search(r"lhs_contracting_dims=\{([\d,]*)\}", rest)
                size = math.prod(first[int(d)] for d in k.group(1).split(",") if d) if k else 1
                counts["arith"] += 2 * out * size
        else:
            for k, names in _OPS.items():
                if op in names:
                    counts[k] += out

    @functools.cache  # a computation's total: its own ops and its callees', as often as called
    def total(c):
        t = dict(own[c])
        for callee, times in callees[c]:
            if callee in own:
                for k, v in total(callee).items():
                    t[k] += times * v
        return t

    return total(entry)


def kernel_op_counts(table: Table) -> dict:
    """Operations per pose of the compiled compensated-command kernel (`hlo_op_counts`)."""
    eff = resolve_effects(table, None)
    N = 4096
    f = jax.jit(jax.vmap(lambda q: inverse_extension(table, eff, q, Context())[0]))
    return hlo_op_counts(f.lower(jnp.zeros((N, 6))).compile().as_text(), N)


def error_map_op_counts(table: Table, cond: bool) -> dict:
    """Operations per pose of the compiled error-map kernel (`hlo_op_counts`): the budget,
    the condition number when `cond`, reachability and the summary's bins."""
    sigmas = Tolerances().sigmas()
    N = 4096
    f = jax.jit(jax.vmap(lambda q: _budget_row((table, sigmas, cond, False), q)))
    return hlo_op_counts(f.lower(jnp.zeros((N, 6))).compile().as_text(), N)


def machine_limit(counts: dict, rates: dict) -> float:
    """Poses per second if every op ran at its measured throughput with nothing else (no
    memory traffic, no overlap between op kinds): 1 / Σ count_k / rate_k."""
    return 1.0 / sum(counts[k] / rates[k] for k in counts if counts[k])


# ---------------------------------------------------------------- the benchmark


_BIG_MAPS = {  # the call and the summary figure each big map reports
    "command": ("jt.command_map(jt.reference_table(), g)", "'spiral_worst_mm'"),
    "error": ("jt.error_map(jt.reference_table(), grid=g, keep=False)", "'cond_max'"),
}


def _map_peak(n_side: int, kind: str = "command") -> dict:
    """Run a command map, or the tolerance error map (full budget with the condition number)
    when `kind` is "error", over an n_side⁴-pose grid (x, y, z, yaw) in a fresh child process
    and return its wall time, compilation included, and peak resident memory (VmHWM:
    getrusage's maxrss would carry the parent's peak over fork and exec)."""
    call, key = _BIG_MAPS[kind]
    code = (
        "import time, json, sys; import numpy as np; import jaxtable as jt;"
        "from jaxtable import Grid;"
        f"n={n_side}; v=lambda h: tuple(np.linspace(-h, h, n));"
        "g=Grid((0,1,2,5),(v(100.0),v(100.0),v(50.0),v(0.17)),(0.0,)*6);"
        f"t0=time.perf_counter(); _, s={call};"
        "dt=time.perf_counter()-t0;"
        "print(json.dumps({'poses': len(g), 'seconds': dt, 'reachable': s['reachable'],"
        "'peak_rss_mib': [int(l.split()[1]) for l in open('/proc/self/status')"
        " if l.startswith('VmHWM')][0]/1024,"
        f"{key}: s[{key}]}}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def run_benchmark(table: Table, quick: bool = False, log=print) -> dict:
    """Measure everything; returns a JSON-able dict. `quick`: tiny sizes (a smoke run)."""
    r = {
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "devices": [str(d) for d in jax.devices()],
            "jax": jax.__version__,
        }
    }
    reps = 2 if quick else 5

    # -- inverse kinematics + spiral
    sizes = [10**3, 10**4] if quick else [10**3, 10**5, 10**6, 10**7]
    rows = []
    for n in sizes:
        q = _poses(n)
        first, t = _timed(lambda q=q: _ready(actuator_command(table, q, check=False)), reps)
        row = {"poses": n, "per_s": n / t, "compile_s": max(first - t, 0.0)}
        if n <= 10**6:
            ref = numpy_command(table, q)
            got = np.asarray(actuator_command(table, q, check=False))
            row["max_diff_mm"] = float(np.max(np.abs(got - ref)))
            _, tn = _timed(lambda q=q: numpy_command(table, q), 1 if n >= 10**6 else reps)
            row["numpy_per_s"] = n / tn
            row["ratio"] = row["per_s"] / row["numpy_per_s"]
        rows.append(row)
        log(
            f"IK+spiral {n:>9} poses: {row['per_s']:.3g}/s"
            + (
                f" (numpy {row['numpy_per_s']:.3g}/s, ×{row['ratio']:.1f})"
                if "ratio" in row
                else ""
            )
        )
    r["ik"] = rows

    # kernel alone (device arrays in and out, no input conversion / output copy)
    n = 10**4 if quick else 10**6
    eff = resolve_effects(table, None)
    kernel = jax.jit(
        jax.vmap(
            lambda T, E, p: T.zero_lengths + inverse_extension(T, E, p)[0], in_axes=(None, None, 0)
        )
    )
    qd = jnp.asarray(_poses(n))
    first, t = _timed(lambda: _ready(kernel(table, eff, qd)), reps)
    rates = _op_rates(1 << 18 if quick else 1 << 22, reps)
    counts = kernel_op_counts(table)
    limit = machine_limit(counts, rates)
    api = next(x for x in rows if x["poses"] == n)["per_s"] if not quick else rows[-1]["per_s"]
    r["ik_limit"] = {
        "poses": n,
        "kernel_per_s": n / t,
        "ops_per_pose": counts,
        "op_rates_per_s": rates,
        "limit_per_s": limit,
        "kernel_fraction": n / t / limit,
        "api_fraction": api / limit,
    }
    log(f"IK kernel {n / t:.3g}/s; machine limit {limit:.3g}/s ({n / t / limit:.0%})")

    # -- forward kinematics
    sizes = [10**2, 10**3] if quick else [10**3, 10**4, 10**5, 10**6]
    n_scipy = 20 if quick else 200
    qs = _poses(n_scipy, seed=1)
    cs = numpy_command(table, qs)
    t0 = time.perf_counter()
    qsol = scipy_forward(table, cs)
    scipy_rate = n_scipy / (time.perf_counter() - t0)
    scipy_err = float(np.max(np.abs(qsol - qs)))
    rows = []
    for n in sizes:
        q = _poses(n, seed=2)
        cmd = np.asarray(actuator_command(table, q))
        t0 = time.perf_counter()
        res = _ready(forward_solve(table, cmd))
        first = time.perf_counter() - t0
        _, t = _timed(lambda cmd=cmd: _ready(forward_solve(table, cmd).pose), 3)
        rows.append(
            {
                "poses": n,
                "per_s": n / t,
                "compile_s": max(first - t, 0.0),
                "converged": float(np.mean(np.asarray(res.ok))),
                "mean_steps": float(np.mean(np.asarray(res.steps))),
                "max_pose_error": float(np.max(np.abs(np.asarray(res.pose) - q))),
                "scipy_per_s": scipy_rate,
                "ratio": n / t / scipy_rate,
            }
        )
        log(
            f"FK {n:>8} poses: {n / t:.3g}/s (scipy fsolve {scipy_rate:.3g}/s, "
            f"×{n / t / scipy_rate:.0f})"
        )
    r["fk"] = rows
    # the IK-based limit: every step evaluates the residual at least once (Newton steps also
    # its Jacobian), so the IK machine limit over the mean step count bounds the solve
    big = rows[-1]
    fk_limit = limit / big["mean_steps"]
    r["fk_limit"] = {
        "poses": big["poses"],
        "mean_steps": big["mean_steps"],
        "limit_per_s": fk_limit,
        "fraction": big["per_s"] / fk_limit,
    }
    log(
        f"FK: {big['mean_steps']:.2f} steps a pose; IK-based limit {fk_limit:.3g}/s "
        f"({big['per_s'] / fk_limit:.0%})"
    )
    r["fk_scipy"] = {"poses": n_scipy, "per_s": scipy_rate, "max_pose_error": scipy_err}

    # -- sensitivities
    n = 10**3 if quick else 10**5
    q = _poses(n, seed=3)
    first, t = _timed(lambda: _ready(pose_sensitivity(table, q)[0]), 3)
    r["sensitivity"] = {
        "poses": n,
        "shape": [6, 42],
        "per_s": n / t,
        "compile_s": max(first - t, 0.0),
    }
    log(f"sensitivities 6×42 over {n} poses: {n / t:.3g} poses/s")

    # -- calibration and posterior
    r["calibration"] = _bench_calibration(table, quick)
    c = r["calibration"]
    log(
        f"calibration {c['parameters']} parameters, {c['poses']} poses: "
        f"{c['fit_s'] * 1e3:.0f} ms ({c['steps']} steps); emcee {c['walker_steps_per_s']:.3g} "
        "walker-steps/s"
    )

    # -- single-pose command latency
    f = command_function(table)
    qs = _poses(2000 if quick else 20000, seed=4)
    lat = _latencies(f, qs)
    trivial = jax.jit(lambda q: q + 1.0)  # JAX's dispatch floor: a call that does nothing
    lat_floor = _latencies(lambda p: np.asarray(trivial(p)), qs[:5000])
    lat_np = _latencies(lambda p: numpy_command(table, p[None]), qs[:5000])
    r["latency"] = {
        "calls": len(qs),
        "median_us": float(np.median(lat) * 1e6),
        "p99_us": float(np.percentile(lat, 99) * 1e6),
        "max_us": float(lat.max() * 1e6),
        "cycle_budget_us": CYCLE_US,
        "dispatch_floor_median_us": float(np.median(lat_floor) * 1e6),
        "dispatch_floor_p99_us": float(np.percentile(lat_floor, 99) * 1e6),
        "numpy_median_us": float(np.median(lat_np) * 1e6),
        "numpy_p99_us": float(np.percentile(lat_np, 99) * 1e6),
    }
    la = r["latency"]
    log(
        f"single-pose command: median {la['median_us']:.1f} µs, p99 {la['p99_us']:.1f} µs "
        f"(numpy {la['numpy_median_us']:.1f} / {la['numpy_p99_us']:.1f} µs); "
        f"budget {CYCLE_US:.0f} µs"
    )

    # -- design criteria batched over designs
    r["designs"] = _bench_designs(table, quick)
    de = r["designs"]
    log(
        f"design criteria, {de['designs']} designs x {de['poses']} poses: {de['seconds']:.1f} s "
        f"({de['design_poses_per_s']:.3g} design-poses/s); numpy loop (subset of the criteria) "
        f"{de['numpy_design_poses_per_s']:.3g} design-poses/s"
    )

    # -- tolerance error map
    r["error_map"] = _bench_error_map(table, quick, rates)
    em = r["error_map"]
    log(
        f"error map (full budget), {em['poses']:.0e} poses: {em['per_s']:.3g} poses/s "
        f"({em['budget_only_per_s']:.3g} without the condition number); machine limit "
        f"{em['limit_per_s']:.3g}/s ({em['per_s'] / em['limit_per_s']:.0%}), without "
        f"{em['budget_only_limit_per_s']:.3g}/s "
        f"({em['budget_only_per_s'] / em['budget_only_limit_per_s']:.0%}); numpy baseline "
        f"{em['numpy_per_s']:.3g}/s (×{em['per_s'] / em['numpy_per_s']:.0f}), largest "
        f"relative difference {em['numpy_max_rel_diff']:.1e}"
    )

    # -- diagnose on the bundled example, cold and warm compilation cache
    if not quick:
        r["diagnose"] = _diagnose_wall()
        dg = r["diagnose"]
        log(
            f"diagnose (bundled example): first {dg['first_s']:.0f} s, "
            f"repeat {dg['repeat_s']:.0f} s"
        )

    # -- big streamed map in a child process (peak memory)
    r["map"] = _map_peak(10 if quick else 100)
    m = r["map"]
    log(
        f"command map {m['poses']:.0e} poses: {m['seconds']:.1f} s, "
        f"{m['poses'] / m['seconds']:.3g}/s, peak RSS {m['peak_rss_mib']:.0f} MiB"
    )
    r["error_map_big"] = _map_peak(10 if quick else 100, "error")
    m = r["error_map_big"]
    log(
        f"error map {m['poses']:.0e} poses: {m['seconds']:.1f} s, "
        f"{m['poses'] / m['seconds']:.3g}/s, peak RSS {m['peak_rss_mib']:.0f} MiB"
    )
    return r


def _bench_calibration(table: Table, quick: bool) -> dict:
    n = 40 if quick else 200
    true = perturb_table(table, seed=11)
    truth = {"spiral": Spiral(12.7 * np.ones(6)), "lead_scale": LeadScale(1e-4)}
    data = simulate(table, true, plan_random(n, seed=12), tracker6(), effects=truth, seed=13)
    model = {"spiral": Spiral.from_table(table), "lead_scale": LeadScale()}
    free = GEOMETRY + ("spiral.lead", "lead_scale.eps")
    st = setup(table, data, free, effects=model)
    t0 = time.perf_counter()
    cal = fit(st)
    first = time.perf_counter() - t0
    _, t = _timed(lambda: fit(st), 2 if quick else 3)
    t0 = time.perf_counter()
    fit(st, method="levenberg_marquardt")
    lm_first = time.perf_counter() - t0
    _, t_lm = _timed(lambda: fit(st, method="levenberg_marquardt"), 2 if quick else 3)
    n_steps = 20 if quick else 200
    t0 = time.perf_counter()
    with warnings.catch_warnings():  # a short chain is expected: only its speed is measured
        warnings.simplefilter("ignore")
        post = posterior(st, cal, n_steps=n_steps, progress=False, burn=n_steps // 2, thin=1)
    t_post = time.perf_counter() - t0
    walkers = post.n_walkers
    return {
        "poses": n,
        "observations": int(cal.n_obs),
        "parameters": len(cal.names),
        "geometric_and_effect_parameters": 42 + 12,
        "rank": int(cal.rank),
        "steps": int(cal.steps),
        "fit_s": t,
        "fit_compile_s": max(first - t, 0.0),
        "noise_iterations": int(cal.noise.iterations),
        "lm_fit_s": t_lm,
        "lm_compile_s": max(lm_first - t_lm, 0.0),
        "mcmc_steps": n_steps,
        "walkers": walkers,
        "mcmc_s": t_post,
        "walker_steps_per_s": walkers * n_steps / t_post,
    }


# ---------------------------------------------------------------- reporting


def _random_designs(table: Table, n: int, seed: int = 0):
    """`n` symmetric designs around the table's (radii, home height ±20 %, pair half angles
    4-20°), stacked for vmap."""
    from jaxtable import Design, SymmetricDesign, hardware_for
    from jaxtable._design.variables import set_values, stack

    d0 = Design(SymmetricDesign.from_table(table), hardware_for(table))
    g = d0.geometry
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        f = rng.uniform(0.8, 1.2, 3)
        ang = np.deg2rad(rng.uniform(4.0, 20.0, 2))
        out.append(
            set_values(
                d0,
                {
                    "base_radius": float(g.base_radius) * f[0],
                    "platform_radius": float(g.platform_radius) * f[1],
                    "home_height": float(g.home_height) * f[2],
                    "base_half_angle": ang[0],
                    "platform_half_angle": ang[1],
                },
            )
        )
    return d0, out, stack


def _bench_designs(table: Table, quick: bool) -> dict:
    """Every design criterion for a population of designs over ~10³ workspace poses, vmapped
    over designs and poses (`assess_designs` runs them in chunks of 64), 1000 designs a call
    (100 in quick mode), against a numpy loop over designs."""
    from jaxtable import Workspace, assess_designs, design_poses

    n_designs = 200 if quick else 10**4
    poses = design_poses(Workspace(), n_sweep=7, n_random=894, box=2)  # 42 + 64 + 894 = 1000
    d0, designs, stack = _random_designs(table, n_designs)
    chunk = 100 if quick else 1000
    t0 = time.perf_counter()
    first = assess_designs(stack(designs[:chunk]), poses)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    results = [first] + [
        assess_designs(stack(designs[i : i + chunk]), poses) for i in range(chunk, n_designs, chunk)
    ]
    t_rest = time.perf_counter() - t0
    per_chunk = t_rest / max(len(results) - 1, 1)
    seconds = t_first - per_chunk + per_chunk * len(results)  # compile counted once
    n_np = 10 if quick else 50
    t0 = time.perf_counter()
    base = [
        numpy_design_criteria(
            d.table(),
            float(d.hardware.leg_stiffness[0]),
            float(d.hardware.moving_mass(d.table())),
            float(d.hardware.acceleration),
            float(d.hardware.characteristic_length),
            np.asarray(d.hardware.inertia),
            poses,
        )
        for d in designs[:n_np]
    ]
    t_np = time.perf_counter() - t0
    diff = max(
        abs(base[i][k] - results[0][k][i]) / abs(base[i][k]) for i in range(n_np) for k in base[0]
    )
    return {
        "designs": n_designs,
        "poses": len(poses),
        "seconds": seconds,
        "compile_s": max(t_first - per_chunk, 0.0),
        "design_poses_per_s": n_designs * len(poses) / seconds,
        "numpy_designs": n_np,
        "numpy_design_poses_per_s": n_np * len(poses) / t_np,
        "numpy_max_rel_diff": diff,
        "criteria": len(first),
    }


def _diagnose_wall(runs: int = 2) -> dict:
    """Wall time of `jaxtable diagnose` on the bundled example, each run a fresh process
    (start-up, tracing, compilation, fits, report and figures), the first with an empty
    persistent compilation cache and the next ones reusing it."""
    import tempfile

    out = {"runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, JAXTABLE_CACHE_DIR=str(Path(tmp) / "cache"))
        for k in range(runs):
            t0 = time.perf_counter()
            subprocess.run(
                [sys.executable, "-m", "jaxtable.cli", "diagnose", "--out", f"{tmp}/d{k}"],
                capture_output=True,
                text=True,
                check=True,
                env=env,
            )
            out["runs"].append(time.perf_counter() - t0)
    out["first_s"] = out["runs"][0]
    out["repeat_s"] = min(out["runs"][1:]) if runs > 1 else float("nan")
    return out


def suite_wall() -> dict:
    """Wall time of the default test suite (`python -m pytest -q`, the README's test command:
    every core, `slow` checks skipped) in a fresh process with an empty persistent
    compilation cache, as on a clean clone; with its pass/fail counts."""
    import tempfile

    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, JAXTABLE_TEST_CACHE=str(Path(tmp) / "cache"))
        t0 = time.perf_counter()
        p = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"],
            cwd=root,
            capture_output=True,
            text=True,
            env=env,
        )
        wall = time.perf_counter() - t0
    counts = {k: int(n) for n, k in re.findall(r"(\d+) (passed|failed|errors?|skipped)", p.stdout)}
    return {"seconds": wall, "returncode": p.returncode, **counts}


def _bench_error_map(table: Table, quick: bool, rates: dict) -> dict:
    """The paper's full tolerance budget (6 sources, std/bias/cond/reachability) over random
    commanded poses, streamed in chunks with the summary statistics; the machine limit of
    its compiled kernel, with and without the condition number (op `rates` as measured for
    the inverse kinematics)."""
    n = 10**4 if quick else 10**6
    q = _poses(n, seed=5)
    first, t = _timed(lambda: error_map(table, grid=q, keep=False), 2 if quick else 3)
    _, t_lean = _timed(lambda: error_map(table, grid=q, keep=False, cond=False), 2 if quick else 3)
    # the numpy baseline (central differences, np.linalg.inv and cond over the poses) on the
    # first poses, and the largest difference from jaxtable's kept map there (float32)
    n_np = 2000 if quick else 20000
    sigmas = np.array(Tolerances().sigmas())
    rho = float(platform_radius(table))
    base = numpy_error_map(table, sigmas, q[:n_np], rho)
    _, t_np = _timed(lambda: numpy_error_map(table, sigmas, q[:n_np], rho), 1 if quick else 2)
    ours, _ = error_map(table, grid=q[:n_np])
    diff = max(
        float(np.max(np.abs(b - np.asarray(o, float)) / np.abs(np.asarray(o, float))))
        for b, o in ((base[0][:, -1], ours.std[:, -1]), (base[2], ours.cond))
    )
    return {
        "poses": n,
        "per_s": n / t,
        "compile_s": max(first - t, 0.0),
        "budget_only_per_s": n / t_lean,
        "numpy_poses": n_np,
        "numpy_per_s": n_np / t_np,
        "numpy_max_rel_diff": diff,
        "ops_per_pose": error_map_op_counts(table, True),
        "budget_only_ops_per_pose": error_map_op_counts(table, False),
        "limit_per_s": machine_limit(error_map_op_counts(table, True), rates),
        "budget_only_limit_per_s": machine_limit(error_map_op_counts(table, False), rates),
    }


def markdown(r: dict) -> str:
    """The benchmark as a Markdown report."""
    L = [
        "# jaxtable benchmark",
        "",
        f"Machine: {r['machine']['cpu_count']} CPU cores, {r['machine']['platform']}, "
        f"jax {r['machine']['jax']}, devices {', '.join(r['machine']['devices'])}. "
        "Each figure is the median of repeated runs after a first (compiling) call; the "
        "compile column is first call − median. Baselines ran in the same process.",
        "",
        "## Inverse kinematics with the spiral term (compensated command)",
        "",
        "| poses | jaxtable poses/s | compile s | numpy poses/s | jaxtable / numpy | max diff mm |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for x in r["ik"]:
        L.append(
            f"| {x['poses']:.0e} | {x['per_s']:.3g} | {x['compile_s']:.2f} | "
            + (
                f"{x['numpy_per_s']:.3g} | {x['ratio']:.1f}× | {x['max_diff_mm']:.1e} |"
                if "ratio" in x
                else "— | — | — |"
            )
        )
    lim = r["ik_limit"]
    c = lim["ops_per_pose"]
    rt = lim["op_rates_per_s"]
    L += [
        "",
        f"Machine limit: the compiled kernel does per pose {c['arith']:.0f} arithmetic ops, "
        f"{c['divide']:.0f} divisions, {c['sqrt']:.0f} sqrt, {c['sin']:.0f} sin, "
        f"{c['cos']:.0f} cos and {c['atan2']:.0f} atan2 (counted in its optimised HLO). "
        f"Measured here over all cores: arithmetic {rt['arith']:.3g}/s, division "
        f"{rt['divide']:.3g}/s, sqrt {rt['sqrt']:.3g}/s, sin {rt['sin']:.3g}/s, cos "
        f"{rt['cos']:.3g}/s, atan2 {rt['atan2']:.3g}/s. With each op at its throughput and "
        f"nothing else: **{lim['limit_per_s']:.3g} poses/s**. The kernel alone (device arrays "
        f"in and out, {lim['poses']:.0e} poses) reaches {lim['kernel_per_s']:.3g}/s = "
        f"{lim['kernel_fraction']:.0%} of it; the public `actuator_command` (numpy in, input "
        f"checks, chunking, copy out) {lim['api_fraction']:.0%}.",
        "",
        "## Forward kinematics (Newton in one while_loop, spiral term inside the solve)",
        "",
        "| poses | jaxtable poses/s | compile s | converged | max pose error | scipy fsolve "
        "poses/s | jaxtable / scipy |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for x in r["fk"]:
        L.append(
            f"| {x['poses']:.0e} | {x['per_s']:.3g} | {x['compile_s']:.2f} | "
            f"{x['converged']:.0%} | {x['max_pose_error']:.1e} | {x['scipy_per_s']:.3g} | "
            f"{x['ratio']:.0f}× |"
        )
    fl = r["fk_limit"]
    L += [
        "",
        f"IK-based limit: at {fl['poses']:.0e} poses the solve takes {fl['mean_steps']:.2f} "
        "steps a pose, each evaluating the residual (one inverse-kinematics kernel) at least "
        f"once, so the IK machine limit over the steps is **{fl['limit_per_s']:.3g} poses/s**; "
        f"forward kinematics reaches {fl['fraction']:.0%} of it.",
    ]
    s = r["fk_scipy"]
    se = r["sensitivity"]
    ca = r["calibration"]
    la = r["latency"]
    m = r["map"]
    eb = r["error_map_big"]
    de = r["designs"]
    L += [
        "",
        f"scipy baseline: `scipy.optimize.fsolve` pose by pose on the numpy model, "
        f"{s['poses']} poses, max pose error {s['max_pose_error']:.1e}.",
        "",
        "## Other workloads",
        "",
        "| workload | figure |",
        "|---|---|",
        f"| sensitivities d(pose)/d(42 geometric parameters), {se['poses']:.0e} poses | "
        f"{se['per_s']:.3g} poses/s (compile {se['compile_s']:.1f} s) |",
        f"| calibration (Gauss–Newton, the default; σ re-estimated: "
        f"{ca['noise_iterations']} fits): {ca['geometric_and_effect_parameters']} "
        f"geometric + effect parameters (+ frame), {ca['poses']} poses of 6-D data "
        f"({ca['observations']} observations, rank {ca['rank']}) | {ca['fit_s'] * 1e3:.0f} ms "
        f'(compile {ca["fit_compile_s"]:.1f} s); with `method="levenberg_marquardt"` '
        f"{ca['lm_fit_s'] * 1e3:.0f} ms (compile {ca['lm_compile_s']:.1f} s) |",
        f"| emcee posterior of that fit, {ca['walkers']} walkers × {ca['mcmc_steps']} steps | "
        f"{ca['walker_steps_per_s']:.3g} walker-steps/s |",
        f"| single-pose compensated command (`command_function`), {la['calls']} calls | "
        f"median {la['median_us']:.1f} µs, p99 {la['p99_us']:.1f} µs, max "
        f"{la['max_us']:.0f} µs; JAX dispatch floor (a jitted no-op, numpy in/out): median "
        f"{la['dispatch_floor_median_us']:.1f} µs, p99 {la['dispatch_floor_p99_us']:.1f} µs; "
        f"numpy one pose: median {la['numpy_median_us']:.1f} µs, p99 "
        f"{la['numpy_p99_us']:.1f} µs |",
        f"| every design criterion ({de['criteria']}: coverage, LCI, budget σ, spiral error, "
        f"stiffness, leg force, motor torque and speed, first frequency, tolerance cost) for "
        f"{de['designs']:.0e} designs × {de['poses']} poses, vmapped over both in chunks of 64 "
        f"designs | {de['seconds']:.0f} s = {de['design_poses_per_s']:.3g} design-poses/s "
        f"(compile {de['compile_s']:.0f} s); numpy loop over {de['numpy_designs']} designs "
        f"computing 5 of the criteria (LCI, GCI, stiffness, leg force, frequency; no budget): "
        f"{de['numpy_design_poses_per_s']:.3g} design-poses/s; largest relative difference "
        f"{de['numpy_max_rel_diff']:.1e} |",
        f"| tolerance error map (6 sources, σ per source, spiral bias, condition number, "
        f"reachability, streamed summary), {r['error_map']['poses']:.0e} random poses | "
        f"{r['error_map']['per_s']:.3g} poses/s (compile {r['error_map']['compile_s']:.1f} s); "
        f"without the condition number (`cond=False`): "
        f"{r['error_map']['budget_only_per_s']:.3g} poses/s; machine limit of its compiled "
        f"kernel (ops counted as for the IK) {r['error_map']['limit_per_s']:.3g} poses/s "
        f"({r['error_map']['per_s'] / r['error_map']['limit_per_s']:.0%}), without the "
        f"condition number {r['error_map']['budget_only_limit_per_s']:.3g} poses/s "
        f"({r['error_map']['budget_only_per_s'] / r['error_map']['budget_only_limit_per_s']:.0%})"
        + (
            f"; numpy baseline (vectorised, central differences, `np.linalg.inv` and `cond` "
            f"over the poses; no reachability or summary), {r['error_map']['numpy_poses']} "
            f"poses: {r['error_map']['numpy_per_s']:.3g} poses/s, jaxtable "
            f"{r['error_map']['per_s'] / r['error_map']['numpy_per_s']:.0f}×; largest "
            f"relative difference of the total σ and the condition number "
            f"{r['error_map']['numpy_max_rel_diff']:.1e} (the kept map is float32)"
            if "numpy_per_s" in r["error_map"]
            else ""
        )
        + " |",
    ]
    if "diagnose" in r:
        L.append(
            f"| `jaxtable diagnose` on the bundled example (150 rows; a fresh process each "
            f"run) | first run (empty compilation cache) {r['diagnose']['first_s']:.0f} s, "
            f"repeat {r['diagnose']['repeat_s']:.0f} s |"
        )
    if "suite" in r:
        su = r["suite"]
        L.append(
            f"| default test suite (`python -m pytest -q`, both cores, empty compilation "
            f"cache) | {su['seconds'] / 60:.1f} min, {su.get('passed', 0)} passed, "
            f"{su.get('failed', 0)} failed |"
        )
    L += [
        f"| streamed command map, {m['poses']:.0e} poses (x, y, z, yaw grid) | "
        f"{m['seconds']:.1f} s = {m['poses'] / m['seconds']:.3g} poses/s, peak resident "
        f"memory {m['peak_rss_mib']:.0f} MiB |",
        f"| streamed tolerance error map (full budget with the condition number), "
        f"{eb['poses']:.0e} poses (the same grid; a fresh process, compilation included) | "
        f"{eb['seconds']:.1f} s = {eb['poses'] / eb['seconds']:.3g} poses/s, peak resident "
        f"memory {eb['peak_rss_mib']:.0f} MiB |",
        "",
        f"Real-time budget assumed: a {la['cycle_budget_us']:.0f} µs (1 kHz) servo cycle; the "
        f"p99 command takes {la['p99_us'] / la['cycle_budget_us']:.1%} of it.",
        "",
    ]
    return "\n".join(L)


def write(r: dict, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    j = out / "benchmark.json"
    j.write_text(json.dumps(r, indent=1))
    md = out / "benchmark.md"
    md.write_text(markdown(r))
    return [j, md]
