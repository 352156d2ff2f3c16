"""Nothing leaves the machine unasked: onnxruntime and OpenVINO run with their telemetry off
whatever the environment (no device id or client id written, no look-up), a local Ray instance
listens on 127.0.0.1 only with usage stats off and no cloud-metadata probe, and a Ray address where
nothing listens fails in bounded time, in one line."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
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


def test_telemetry_off_whatever_the_environment(tmp_path):
    """A user's ``ORT_DISABLE_TELEMETRY=0`` does not turn onnxruntime's telemetry back on, and
    ``openvino_telemetry`` cannot be imported once msdnet.runtime is."""
    code = (
        "import os, msdnet.runtime\n"
        "try:\n    import openvino_telemetry\n    print('imported')\n"
        "except ImportError:\n    print('blocked')\n"
        "print(os.environ['ORT_DISABLE_TELEMETRY'], os.environ['ORT_TELEMETRY_DISABLED'])"
    )
    env = _clean_env(tmp_path) | {"ORT_DISABLE_TELEMETRY": "0", "ORT_TELEMETRY_DISABLED": "0"}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.split() == ["blocked", "1", "1"], r.stdout + r.stderr


# ---------------------------------------------------------------- first runs at the default provider

TRACE = shutil.which("strace")
LOOPBACK = ("127.", "::1", "::ffff:127.")


def _first_run_env(home: Path) -> dict[str, str]:
    """A fresh HOME (no engine cache, no consent files) and none of the engines' opt-out variables."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ORT_", "OPENVINO", "XDG_"))}
    env.pop("CI", None)  # openvino_telemetry also stays quiet in CI: the test must not lean on that
    return env | {"HOME": str(home)}


def _traced(cmd: list[str], trace: Path) -> list[str]:
    """``cmd`` under strace (every thread and child) recording its sockets' network system calls."""
    calls = "trace=socket,setsockopt,connect,sendto,sendmsg"
    return [TRACE, "-f", "-qq", "-e", calls, "-o", str(trace), *cmd]


def _remote_calls(trace: Path) -> list[str]:
    """Lines of an strace log that connect or send to an IPv4 / IPv6 address off loopback.

    Cyclone DDS probes once at start whether multicast loops back, even with multicast off: a
    16-byte datagram to 239.255.0.1 from a socket whose multicast interface is 127.0.0.1 and whose
    multicast TTL is 0, which the kernel never lets past this host. Sends from such a socket count
    as local; any other multicast or unicast send off loopback is reported.
    """
    ttl0: set[tuple[str, str]] = set()  # (pid, fd) of sockets with multicast TTL 0
    on_lo: set[tuple[str, str]] = set()  # (pid, fd) of sockets with multicast interface 127.0.0.1
    bad = []
    for line in trace.read_text(errors="replace").splitlines():
        call = re.match(r"(\d+)\s+(\w+)\((\d+)?", line)
        if call is None:
            continue
        pid, name, fd = call.groups()
        if name == "socket":
            ret = re.search(r"= (\d+)$", line)
            if ret:  # a new socket on this fd: forget what the fd was before
                ttl0.discard((pid, ret.group(1)))
                on_lo.discard((pid, ret.group(1)))
            continue
        if name == "setsockopt":
            if "IP_MULTICAST_TTL" in line and '"\\0"' in line:
                ttl0.add((pid, fd))
            if "IP_MULTICAST_IF, [16777343]" in line:  # 127.0.0.1
                on_lo.add((pid, fd))
            continue
        if name not in ("connect", "sendto", "sendmsg") or "AF_INET" not in line:
            continue
        addr = re.search(r'inet_(?:addr|pton)\((?:AF_INET6, )?"([^"]+)"', line)
        if addr is not None and addr.group(1).startswith(LOOPBACK):
            continue
        if addr is not None and addr.group(1).startswith("239.") and {(pid, fd)} <= ttl0 & on_lo:
            continue
        bad.append(line)
    return bad


def _home_written(home: Path) -> list[str]:
    """What an engine wrote under HOME: OpenVINO's ``~/intel``, onnxruntime's ``~/.cache/Microsoft``."""
    return sorted(str(p.relative_to(home)) for d in ("intel", ".cache/Microsoft") for p in home.glob(d + "*"))


@pytest.mark.skipif(TRACE is None, reason="needs strace (Debian package strace)")
def test_first_infer_at_default_provider_sends_nothing(scan, tmp_path):
    """``msdnet-infer`` with the default provider (auto: onnxruntime and OpenVINO measured in the
    process on a first run) writes no telemetry file and reaches no address off loopback."""
    home, trace = tmp_path / "home", tmp_path / "trace.txt"
    home.mkdir()
    for i in range(2):  # three scans, as a first user would
        (np.random.default_rng(i + 1).random((40, 7)) * 8).astype("<f4").tofile(scan.parent / f"s{i}.bin")
    cmd = [sys.executable, "-c", "from msdnet.runtime.frontends.infer.cli import main; main()"]
    cmd += [str(scan.parent), "--out", str(tmp_path / "o")]
    r = subprocess.run(
        _traced(cmd, trace), env=_first_run_env(home), capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr
    assert "provider auto: measured" in r.stderr + r.stdout  # the first-run path really ran
    assert len(list((tmp_path / "o").glob("*.npy"))) == 3
    assert _home_written(home) == []
    assert _remote_calls(trace) == []


@pytest.mark.skipif(TRACE is None, reason="needs strace (Debian package strace)")
def test_first_node_at_default_provider_sends_nothing(tmp_path):
    """``msdnet-node`` at the default provider on a first run: no telemetry file, and DDS aside
    (on loopback by its configuration) nothing reaches an address off loopback."""
    pytest.importorskip("cyclonedds", reason="the [live] extra (CI installs it)")
    psutil = pytest.importorskip("psutil")
    from msdnet.runtime.frontends.live.dds import loopback_env

    home, trace = tmp_path / "home", tmp_path / "trace.txt"
    home.mkdir()
    env = _first_run_env(home) | {"CYCLONEDDS_URI": loopback_env(tmp_path)["CYCLONEDDS_URI"]}
    cmd = [
        sys.executable,
        "-m",
        "msdnet.runtime.frontends.live.cli",
        "--topic",
        "/radar/points",
        "--domain-id",
        "17",
    ]
    proc = subprocess.Popen(
        _traced(cmd, trace), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        ready = proc.stdout.readline()
        assert "serving" in ready, ready + proc.stderr.read()
        time.sleep(1.0)
    finally:
        for child in psutil.Process(proc.pid).children():  # the node itself, not strace
            child.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert "provider auto" in err  # the engines were measured in this process
    assert _home_written(home) == []
    assert _remote_calls(trace) == []


def test_ci_script_sets_it_for_the_tests():
    text = (Path(__file__).resolve().parents[1] / ".ci" / "run").read_text()
    assert "ORT_DISABLE_TELEMETRY=1" in text and "RAY_USAGE_STATS_ENABLED=0" in text


# ---------------------------------------------------------------- Ray


def _infer(*args) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


@pytest.fixture
def scan(tmp_path) -> Path:
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
