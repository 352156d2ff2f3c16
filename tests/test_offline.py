"""Nothing leaves the machine unasked (issue 24): onnxruntime runs with its telemetry off (no
device id written), a local Ray instance listens on 127.0.0.1 only with usage stats off and no
cloud-metadata probe, and a Ray address where nothing listens fails in bounded time, in one line."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from msdnet.runtime.frontends.infer.cli import main

SESSION = """
import time
import numpy as np
from msdnet.runtime import Pipeline
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL
pipe = Pipeline.from_dir(BUNDLED_MODEL, threads=1)
pipe(np.random.default_rng(0).random((50, 5)).astype(np.float32) * 8, steps=1)
time.sleep(2.0)  # onnxruntime writes its device id early; give it time
import os
print(os.environ["ORT_DISABLE_TELEMETRY"], os.environ["ORT_TELEMETRY_DISABLED"])
"""


def _clean_env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ORT_")}
    return env | {"HOME": str(home)}


def test_onnxruntime_session_writes_no_device_id(tmp_path):
    r = subprocess.run(
        [sys.executable, "-c", SESSION], env=_clean_env(tmp_path), capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["1", "1"]  # set for the process by msdnet.runtime
    assert not (tmp_path / ".cache" / "Microsoft").exists(), sorted(map(str, tmp_path.rglob("*")))


def test_user_setting_kept(tmp_path):
    code = "import os, msdnet.runtime; print(os.environ['ORT_DISABLE_TELEMETRY'])"
    env = _clean_env(tmp_path) | {"ORT_DISABLE_TELEMETRY": "0"}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "0", r.stderr


def test_ci_script_sets_it_for_the_tests():
    text = (Path(__file__).resolve().parents[1] / ".ci" / "run").read_text()
    assert "ORT_DISABLE_TELEMETRY=1" in text and "RAY_USAGE_STATS_ENABLED=0" in text


# ---------------------------------------------------------------- Ray


def _infer(*args) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


@pytest.fixture
def scan(tmp_path) -> Path:
    import numpy as np

    folder = tmp_path / "radar"
    folder.mkdir()
    (np.random.default_rng(0).random((40, 7)) * 8).astype("<f4").tofile(folder / "s.bin")
    return folder / "s.bin"


def test_workers_with_ray_refused(scan, tmp_path):
    r = _infer(scan, "--out", tmp_path / "o", "--workers", "2", "--ray")
    assert r.exit_code == 2
    assert r.output == "error: --workers: not with --ray (Ray runs one actor per --threads CPUs)\n"
    assert not (tmp_path / "o").exists()


def test_ray_address_where_nothing_listens_fails_in_bounded_time(scan, tmp_path):
    pytest.importorskip("ray", reason="the [ray] extra (CI installs it)")
    import socket

    with socket.socket() as s:  # a free port: nothing listens there once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    start = time.perf_counter()
    r = _infer(scan, "--out", tmp_path / "o", "--ray", f"127.0.0.1:{port}", "--ray-timeout", "2")
    took = time.perf_counter() - start
    assert r.exit_code == 2, r.output
    assert r.output.startswith(f"error: --ray: nothing answers at 127.0.0.1:{port} within 2 s")
    assert r.output.count("\n") == 1 and took < 10, (took, r.output)
    assert not list((tmp_path / "o").glob("*.npy"))


def test_ray_timeout_must_be_positive(scan, tmp_path):
    r = _infer(scan, "--out", tmp_path / "o", "--ray", "auto", "--ray-timeout", "0")
    assert r.exit_code == 2 and "--ray-timeout" in r.output


def test_local_ray_stays_on_loopback_without_usage_stats_or_metadata_probe(monkeypatch):
    ray = pytest.importorskip("ray", reason="the [ray] extra (CI installs it)")
    psutil = pytest.importorskip("psutil")
    from ray._common.usage import usage_lib

    from msdnet.runtime.frontends.infer.ray_batch import BOOTSTRAP_CONFIG, local_instance

    if ray.is_initialized():
        pytest.skip("this process is already connected to Ray")
    home = os.environ.get("HOME")
    with local_instance(num_cpus=1):
        assert os.environ.get("HOME") == home  # the driver's environment is left as it was
        node = ray._private.worker._global_node
        assert node.node_ip_address == "127.0.0.1"
        assert ray.get_runtime_context().gcs_address.startswith("127.0.0.1:")
        procs = [p.process.pid for ps in node.all_processes.values() for p in ps]
        kids = {c.pid for pid in procs for c in psutil.Process(pid).children(recursive=True)}
        pids = set(procs) | kids | {os.getpid()}
        listening = {
            c.laddr.ip for c in psutil.net_connections("inet") if c.status == "LISTEN" and c.pid in pids
        }
        assert listening and listening <= {"127.0.0.1", "::ffff:127.0.0.1"}, listening
        dash = node.all_processes["dashboard"][0].process.pid  # where Ray's usage module runs
        env = dict(e.split("=", 1) for e in Path(f"/proc/{dash}/environ").read_text().split("\0") if "=" in e)
        assert env.get("RAY_USAGE_STATS_ENABLED") == "0"
        config = Path(env["HOME"]) / BOOTSTRAP_CONFIG

        def probe() -> str:
            raise AssertionError("Ray asked a cloud metadata address")

        monkeypatch.setattr(usage_lib, "get_cloud_from_metadata_requests", probe)
        assert usage_lib.get_cluster_config_to_report(str(config)).cloud_provider == "local"
    assert not config.exists()  # the private folder goes with the instance


def test_a_second_local_ray_instance_in_the_same_process_starts(monkeypatch):
    """Ray turns token auth on at its first local init and caches the token; the next instance's
    private HOME has no token file, so without ``RAY_AUTH_TOKEN`` its GCS server aborted and
    ray.init waited out the GCS port timeout (CI, 2026-12-02)."""
    ray = pytest.importorskip("ray", reason="the [ray] extra (CI installs it)")
    from msdnet.runtime.frontends.infer.ray_batch import local_instance

    if ray.is_initialized():
        pytest.skip("this process is already connected to Ray")
    monkeypatch.setenv("RAY_gcs_server_port_wait_time_s", "20")  # a failure in 20 s, not 120
    token = os.environ.get("RAY_AUTH_TOKEN")
    for _ in range(2):
        with local_instance(num_cpus=1):
            assert ray.get(ray.put(7)) == 7
        assert os.environ.get("RAY_AUTH_TOKEN") == token  # the driver's environment is left as it was
