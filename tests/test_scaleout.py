"""Batch APIs on 2 simulated CPU devices and as 2 processes of a jax.distributed job give
the single-device results (tests/scaleout_worker.py runs the same calls in each setting)."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

WORKER = Path(__file__).with_name("scaleout_worker.py")
TIMEOUT = 300  # s; a deadlock fails the test instead of hanging the suite
KEYS = ("cmd", "fk_pose", "sens", "map_total", "cmap_spiral", "mc", "sim")


def _env(devices: int = 1) -> dict:
    env = dict(os.environ)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "device_count" not in f]
    if devices > 1:
        flags.append(f"--xla_force_host_platform_device_count={devices}")
    env["XLA_FLAGS"] = " ".join(flags)
    env["JAX_PLATFORMS"] = "cpu"
    return env


def _run(out: Path, *args, devices: int = 1):
    return subprocess.Popen(
        [sys.executable, str(WORKER), str(out), *map(str, args)],
        env=_env(devices),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _wait(proc) -> None:
    try:
        log, _ = proc.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"scale-out worker timed out after {TIMEOUT} s (deadlock?)")
    assert proc.returncode == 0, log[-3000:]


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    out = tmp_path_factory.mktemp("scaleout") / "single.npz"
    _wait(_run(out))
    r = np.load(out)
    assert int(r["devices"]) == 1 and int(r["mesh"]) == 0
    return r


def _same(a, b):
    for k in KEYS:
        np.testing.assert_allclose(b[k], a[k], rtol=0, atol=1e-9, err_msg=k)
    np.testing.assert_array_equal(b["fk_ok"], a["fk_ok"])
    assert np.all(a["fk_ok"])


def test_two_simulated_cpu_devices_equal_one(single, tmp_path):
    out = tmp_path / "two_devices.npz"
    _wait(_run(out, devices=2))
    r = np.load(out)
    assert int(r["devices"]) == 2 and int(r["mesh"]) == 2  # the batch was sharded over both
    _same(single, r)


def test_two_processes_over_loopback_equal_one(single, tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    outs = [tmp_path / f"process{i}.npz" for i in range(2)]
    procs = [_run(outs[i], i, 2, port) for i in range(2)]
    for p in procs:
        _wait(p)
    for out in outs:
        r = np.load(out)
        assert int(r["processes"]) == 2 and int(r["devices"]) == 2
        _same(single, r)
