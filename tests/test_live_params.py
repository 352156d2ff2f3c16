"""msdnet-node's parameters file: read within the limits a config file deserves (size, encoding,
depth, aliases, duplicate keys), each refused in one line naming the file; the node's name and
namespace pick the sections that apply, as ROS 2 does."""

from __future__ import annotations

import gzip
import subprocess
import sys
import time
from pathlib import Path

import pytest

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.live import params

NODE = [sys.executable, "-m", "msdnet.runtime.frontends.live.cli"]
GOOD = "msdnet_node:\n  ros__parameters:\n    threads: 1\n    target_frame: base\n"
# 300 bytes that expand to 9**6 strings: refused from its events, never expanded
BOMB = (
    'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    + "".join(f"{b}: &{b} [{','.join([f'*{a}'] * 9)}]\n" for a, b in zip("abcde", "bcdef", strict=True))
    + "msdnet_node:\n  ros__parameters:\n    fields: *f\n"
)
# few aliases, each list four of the one before: 4**8 values once expanded
WIDE = (
    "a: &a [1, 2, 3, 4]\n"
    + "".join(f"{b}: &{b} [*{a}, *{a}, *{a}, *{a}]\n" for a, b in zip("abcdefg", "bcdefgh", strict=True))
    + "msdnet_node:\n  ros__parameters:\n    fields: *h\n"
)

HEAD = b"msdnet_node:\n  ros__parameters:\n"
CASES = {
    "latin-1": (GOOD.replace("base", "bâse").encode("latin-1"), "is not UTF-8 text (byte 0xe2"),
    "utf-16": (GOOD.encode("utf-16"), "is UTF-16"),
    "utf-16 without a byte-order mark": (GOOD.encode("utf-16-le"), "is UTF-16"),
    "gzip": (gzip.compress(GOOD.encode()), "is gzip-compressed"),
    "NUL byte": (GOOD.encode().replace(b"base", b"ba\x00se"), "NUL byte"),
    "too large": (GOOD.encode() + b"#" * 300_000, "larger than 256 KiB"),
    "deep": (b"msdnet_node:\n  ros__parameters:\n    fields: " + b"[" * 20_000 + b"]" * 20_000, "nest"),
    "alias bomb": (BOMB.encode(), "more than 32 YAML aliases"),
    "alias expansion": (WIDE.encode(), "expands through its aliases to more than 10000 values"),
    "self-referring alias": (b"a: &a [*a]\nmsdnet_node:\n  ros__parameters:\n    fields: *a\n", "expands"),
    "duplicate key": (GOOD.encode() + b"    threads: 2\n", "key 'threads' given twice"),
    "python tag": (
        HEAD + b"    threads: !!python/object:os.system x\n",
        "not YAML",
    ),
    "empty": (b"", "expected '<node name>: ros__parameters: ...' at the top"),
    "value out of range": (
        HEAD + b"    domain_id: 300\n",
        "domain_id: must be <= 232",
    ),
    "control character": (
        HEAD + b'    stats_json: "a\\0b"\n',
        "control character",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_bad_parameters_file_is_one_line_naming_it(tmp_path, case: str) -> None:
    data, says = CASES[case]
    path = tmp_path / "node.yaml"
    path.write_bytes(data)
    start = time.monotonic()
    r = subprocess.run(NODE + ["--params-file", str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.startswith(f"error: {path}: ") and says in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and len(r.stderr) < 400 and "Traceback" not in r.stderr
    assert time.monotonic() - start < 20  # refused at once, nothing expanded or loaded


def _values(tmp_path: Path, text: str, **flags: str) -> dict:
    path = tmp_path / "node.yaml"
    path.write_text(text, encoding="utf-8")
    given = set(flags)
    return params.file_values(path, {**dict.fromkeys(p.name for p in params.PARAMS), **flags}, given)


def test_sections_follow_the_node_name_and_namespace(tmp_path) -> None:
    text = (
        "/**:\n  ros__parameters:\n    threads: 4\n    stats_every: 7\n"
        "msdnet_node:\n  ros__parameters:\n    threads: 1\n"
        "/sensing/front:\n  ros__parameters:\n    threads: 2\n"
        "sensing:\n  rear:\n    ros__parameters:\n      threads: 3\n"
        "/sensing/*:\n  ros__parameters:\n    seed: 5\n"
    )
    assert _values(tmp_path, text) == {"threads": 1, "stats_every": 7}
    front = _values(tmp_path, text, node_name="front", namespace="/sensing")
    assert front == {"threads": 2, "stats_every": 7, "seed": 5}  # the msdnet_node section is another node's
    assert _values(tmp_path, text, node_name="rear", namespace="sensing")["threads"] == 3  # nested form
    # the file may name the node itself, in its msdnet_node (or /**) section
    named = "msdnet_node:\n  ros__parameters:\n    node_name: front\n    namespace: /sensing\n    seed: 1\n"
    got = _values(tmp_path, named + "/sensing/front:\n  ros__parameters:\n    seed: 2\n")
    assert got["node_name"] == "front" and got["seed"] == 2  # the node's own section wins
    with pytest.raises(MsdnetError, match="no 'other: ros__parameters:' section"):
        _values(tmp_path, "msdnet_node:\n  ros__parameters:\n    threads: 1\n", node_name="other")
    with pytest.raises(MsdnetError, match="node_name: 'x' differs from the node of section /front"):
        _values(tmp_path, "/front:\n  ros__parameters:\n    node_name: x\n", node_name="front")


def test_print_params_with_a_name_and_namespace_reads_back_the_same(tmp_path) -> None:
    flags = ["--node-name", "radar_front", "--namespace", "/sensing", "--diagnostics-period", "0.5"]
    dumped = subprocess.run(NODE + [*flags, "--print-params"], capture_output=True, text=True, timeout=60)
    assert dumped.returncode == 0, dumped.stderr
    path = tmp_path / "node.yaml"
    path.write_text(dumped.stdout, encoding="utf-8")
    again = subprocess.run(
        NODE + ["--params-file", str(path), "--print-params"], capture_output=True, text=True
    )
    assert again.stdout == dumped.stdout and "diagnostics_period_s: 0.5" in again.stdout


def test_the_stats_json_overwrites_no_input(tmp_path) -> None:
    path = tmp_path / "node.yaml"
    path.write_text("msdnet_node:\n  ros__parameters:\n    threads: 1\n", encoding="utf-8")
    r = subprocess.run(
        NODE + ["--params-file", str(path), "--stats-json", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "is the parameters file: it would be overwritten" in r.stderr, r.stderr
    assert path.read_text(encoding="utf-8").startswith("msdnet_node:")
