"""`python -m benchmarks.device [--scale K] [--out FILE]`: the batch calls on JAX's default
device (a GPU where one is installed) and the same numbers against the same machine's CPU
device.

Measures `actuator_command` (10⁶ and 10⁷ poses), `forward_solve` (10⁵ and 10⁶, with
convergence and the round-trip error), `error_map` with and without the condition number
(10⁶ poses at the default chunk, 10⁷ at chunks of 2²⁰ and 2²²), and compares commands and a
50,000-pose error map with the CPU device's. `--scale K` divides every size by K (a smoke
run: `--scale 1000` takes about a minute on a CPU). Prints one JSON line a measurement and
writes them all to FILE (default: device.json in the working directory). On a GPU, set
`XLA_PYTHON_CLIENT_PREALLOCATE=false` if anything else shares the card."""

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np

import jaxtable as jt

from .bench import _poses, _timed


def run(scale: int = 1, log=print) -> dict:
    """Every measurement of the module docstring; sizes divided by `scale`."""
    jax.config.update("jax_enable_x64", True)
    device, cpu = jax.devices()[0], jax.devices("cpu")[0]
    table = jt.reference_table()
    out = {"jax": jax.__version__, "device": str(device), "platform": device.platform}
    log(json.dumps(out))

    def put(key, value):
        out[key] = value
        log(f"{key} {json.dumps(value)}")

    for n in (10**6 // scale, 10**7 // scale):
        q = _poses(n, 0)
        first, t = _timed(lambda q=q: np.asarray(jt.actuator_command(table, q, check=False)), 3)
        put(f"command_{n}", {"per_s": n / t, "first_s": first})
    q = _poses(20_000, 1)
    here = np.asarray(jt.actuator_command(table, q, check=False))
    with jax.default_device(cpu):
        there = np.asarray(jt.actuator_command(table, q, check=False))
    put("command_vs_cpu_max_mm", float(np.abs(here - there).max()))

    for n in (10**5 // scale, 10**6 // scale):
        q = _poses(n, 2)
        cmd = np.asarray(jt.actuator_command(table, q))
        first, t = _timed(lambda cmd=cmd: np.asarray(jt.forward_solve(table, cmd).pose), 2)
        res = jt.forward_solve(table, cmd)
        put(
            f"forward_{n}",
            {
                "per_s": n / t,
                "first_s": first,
                "converged": float(np.mean(np.asarray(res.ok))),
                "max_pose_error": float(np.abs(np.asarray(res.pose) - q).max()),
            },
        )

    for n, chunk in ((10**6, 1 << 16), (10**7, 1 << 20), (10**7, 1 << 22)):
        n //= scale
        q = _poses(n, 5)
        first, t = _timed(lambda q=q, c=chunk: jt.error_map(table, grid=q, keep=False, chunk=c), 2)
        _, lean = _timed(
            lambda q=q, c=chunk: jt.error_map(table, grid=q, keep=False, chunk=c, cond=False), 2
        )
        put(f"error_map_{n}_{chunk}", {"per_s": n / t, "first_s": first, "without_cond": n / lean})
    q = _poses(50_000, 6)
    m, s = jt.error_map(table, grid=q)
    with jax.default_device(cpu):
        mc, sc = jt.error_map(table, grid=q)

    def rel(a, b):
        return float(np.nanmax(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))

    put(
        "error_map_vs_cpu",
        {
            "std_rel": rel(m.std, mc.std),
            "cond_rel": rel(m.cond, mc.cond),
            "bias_max_mm": float(np.abs(m.bias - mc.bias).max()),
            "reachable_same": bool((m.reachable == mc.reachable).all()),
            "cond_max_rel": abs(s["cond_max"] / sc["cond_max"] - 1),
        },
    )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.device", description=__doc__)
    p.add_argument("--scale", type=int, default=1, help="divide every size by this")
    p.add_argument("--out", type=Path, default=Path("device.json"))
    args = p.parse_args(argv)
    if args.scale < 1:
        p.error("--scale must be a positive integer")
    r = run(args.scale, log=lambda m: print(m, flush=True))
    args.out.write_text(json.dumps(r, indent=1) + "\n")
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
