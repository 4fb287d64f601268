"""Runs the batch APIs on a fixed small problem and saves the results (npz), for the
scale-out tests: the same script on 1 device, on 2 simulated CPU devices and as 2 processes of
a `jax.distributed` job must give the same numbers.

    python tests/scaleout_worker.py OUT.npz                       # this process's devices
    python tests/scaleout_worker.py OUT.npz PROCESS_ID 2 PORT     # one of 2 processes

Set XLA_FLAGS=--xla_force_host_platform_device_count=2 (before start) for 2 CPU devices.
"""

import sys

import jax

jax.config.update("jax_enable_x64", True)
if len(sys.argv) > 2:
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=f"127.0.0.1:{sys.argv[4]}",
        num_processes=int(sys.argv[3]),
        process_id=int(sys.argv[2]),
        initialization_timeout=60,
    )

import numpy as np  # noqa: E402

import jaxtable as jt  # noqa: E402

# the compilation cache the tests share ($JAXTABLE_CACHE_DIR, set by conftest.py): a repeat
# run reads this worker's programs instead of compiling them again
jt.enable_compilation_cache()
table = jt.reference_table()
rng = np.random.default_rng(7)
box = np.array([100.0, 100.0, 50.0, 0.1, 0.1, 0.15])
poses = rng.uniform(-1, 1, (37, 6)) * box  # odd size: padding to the device count is exercised
# chunk 8 < 37 rows: several chunks, the last one padded
cmd = np.asarray(jt.actuator_command(table, poses, chunk=8))
fk = jt.forward_solve(table, cmd, chunk=8)
sens, _ = jt.pose_sensitivity(table, poses[:11], chunk=4)
_, summary = jt.error_map(table, grid=poses[:13], keep=False, chunk=5)
_, cmap = jt.command_map(table, jt.workspace_slice(("x", "yaw"), n=(7, 5)), chunk=9)
mc = jt.monte_carlo(table, jt.Tolerances(), poses[:3], n_samples=5, seed=1)
meas = jt.simulate(table, jt.perturb_table(table, seed=2), poses[:9], jt.tracker6(), seed=3)
np.savez(
    sys.argv[1],
    devices=len(jax.devices()),
    processes=jax.process_count(),
    mesh=0 if jt.batch_mesh() is None else jt.batch_mesh().size,
    cmd=cmd,
    fk_pose=np.asarray(fk.pose),
    fk_ok=np.asarray(fk.ok),
    sens=np.asarray(sens),
    map_total=summary["sources"]["total"]["trans_max_mm"],
    cmap_spiral=np.asarray(cmap["spiral_max_mm"]),
    mc=mc,
    sim=meas.measured,
)
