"""Fuzz of every reader (issue 24): seeded byte mutations and truncations of valid PLY, PCD, NPY,
BIN, Astyx TXT files and PointCloud2 messages are read or refused in one line (``MsdnetError``),
never another exception, a hang or a temporary file left (``benchmarks/fuzz``). 300 cases per
reader here (about 10 s in all); ``msdnet-bench fuzz --cases N`` runs longer."""

from __future__ import annotations

import importlib.util

import pytest
from click.testing import CliRunner

from msdnet.benchmarks import fuzz
from msdnet.benchmarks.cli import main as bench

CASES = 300
HAVE_ROS = importlib.util.find_spec("rosbags") is not None
READERS = fuzz.READERS if HAVE_ROS else tuple(r for r in fuzz.READERS if r != "msg")


@pytest.fixture(scope="module")
def tallies(tmp_path_factory) -> dict[str, fuzz.Tally]:
    return fuzz.run_fuzz(tmp_path_factory.mktemp("fuzz"), CASES, seed=0, readers=READERS)


@pytest.mark.parametrize("reader", READERS)
def test_every_mutated_input_is_read_or_refused_in_one_line(tallies, reader):
    t = tallies[reader]
    assert t.failures == [], "\n".join(t.failures[:10])
    assert t.read + t.refused == CASES
    assert t.read > 0 and t.refused > 0  # the mutations reach both outcomes, not only one


def test_valid_seeds_are_read(tmp_path):
    """The unmutated inputs all read (so every refusal in the fuzz is the mutation's doing)."""
    seeds = fuzz.valid_inputs(tmp_path, seed=0)
    for reader in READERS:
        for name, data in seeds[reader]:
            if reader == "msg":
                fuzz._read_message(data)
            else:
                fuzz._read_file(tmp_path / f"v_{name}", data, tmp_path)


def test_mutations_are_seeded_and_change_the_bytes():
    import numpy as np

    data = bytes(range(256)) * 4
    a = [fuzz.mutate(data, np.random.default_rng([0, 0, i])) for i in range(50)]
    b = [fuzz.mutate(data, np.random.default_rng([0, 0, i])) for i in range(50)]
    assert a == b and sum(m != data for m in a) >= 45
    assert any(len(m) < len(data) // 2 for m in a)  # truncations among them


def test_a_reader_that_raises_something_else_is_a_failure(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise KeyError("vertex")

    monkeypatch.setattr(fuzz, "read_cloud", broken)
    t = fuzz.run_fuzz(tmp_path, 5, seed=0, readers=("bin",))["bin"]
    assert len(t.failures) == 5 and t.failures[0].startswith("bin case 0 (seed 0, from seed.bin): KeyError")


def test_bench_command(tmp_path):
    out = tmp_path / "fuzz.json"
    r = CliRunner().invoke(bench, ["fuzz", "--cases", "20", "--reader", "ply", "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert r.output.startswith("fuzz: 20 cases per reader, seed 0\n  ply  read")
    assert '"ply"' in out.read_text()
