"""Rulebooks against brute-force numpy references, and the rule semantics the network relies on."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msdnet.benchmarks.numpy_reference import down_rulebook_numpy, subm_rulebook_numpy
from msdnet.runtime.engine.rulebook import (
    batch_coords,
    build_encoder_rulebooks,
    down_rulebook,
    down_shape,
    subm_rulebook,
    warmup,
)


def random_coords(rng: np.random.Generator, shape: tuple[int, int, int], batch: int, fill: float):
    """(V, 4) int32 [b, z, y, x]: each sample a random voxel set, sorted by linear index."""
    cells = int(np.prod(shape))
    parts = []
    for _ in range(batch):
        n = rng.binomial(cells, fill)
        lin = np.sort(rng.choice(cells, size=n, replace=False))
        parts.append(np.stack(np.unravel_index(lin, shape), axis=1))  # (n, 3) [z, y, x]
    return batch_coords(parts)


def test_warmup_then_two_neighbours() -> None:
    warmup()  # compiles every kernel once so the rest of the suite is fast
    coords = np.array([[0, 1, 1, 1], [0, 1, 1, 2]], np.int32)
    rules = subm_rulebook(coords, (3, 3, 4))
    assert rules.shape == (2, 27) and rules.dtype == np.int32
    expected = np.full((2, 27), 2, np.int32)
    expected[0, 13], expected[0, 14] = 0, 1  # centre, +x
    expected[1, 12], expected[1, 13] = 0, 1  # -x, centre
    np.testing.assert_array_equal(rules, expected)


shapes = st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 64))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=shapes,
    batch=st.integers(1, 3),
    fill=st.sampled_from([0.0, 0.02, 0.1, 0.6]),
)
def test_subm_matches_reference(seed: int, shape: tuple, batch: int, fill: float) -> None:
    coords = random_coords(np.random.default_rng(seed), shape, batch, fill)
    rules = subm_rulebook(coords, shape)
    np.testing.assert_array_equal(rules, subm_rulebook_numpy(coords, shape))
    v = len(coords)
    np.testing.assert_array_equal(rules[:, 13], np.arange(v))  # centre tap is the voxel itself
    i, k = np.nonzero(rules < v)  # symmetry: j neighbours i by k  <=>  i neighbours j by 26 - k
    np.testing.assert_array_equal(rules[rules[i, k], 26 - k], i)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=st.tuples(st.integers(3, 9), st.integers(3, 9), st.integers(3, 64)),  # wide x: sparse rows
    batch=st.integers(1, 3),
    fill=st.sampled_from([0.0, 0.02, 0.1, 0.6]),
    stride=st.integers(1, 3),
    padding=st.integers(0, 2),
)
def test_down_matches_reference(
    seed: int, shape: tuple, batch: int, fill: float, stride: int, padding: int
) -> None:
    coords = random_coords(np.random.default_rng(seed), shape, batch, fill)
    out, rules, out_shape = down_rulebook(coords, shape, stride, padding)
    ref_out, ref_rules, ref_shape = down_rulebook_numpy(coords, shape, stride, padding)
    assert out_shape == ref_shape == down_shape(shape, stride, padding)
    np.testing.assert_array_equal(out, ref_out)
    np.testing.assert_array_equal(rules, ref_rules)
    v = len(coords)
    assert out.dtype == np.int32 and rules.shape == (len(out), 27)
    assert np.all((rules < v).any(axis=1))  # every output is fed by some input
    if stride == 2 and padding == 1:  # every input feeds some output
        assert set(rules[rules < v].tolist()) == set(range(v))


def test_down_rules_point_at_the_right_inputs() -> None:
    coords = np.array([[0, 0, 0, 0], [0, 1, 2, 3], [0, 3, 3, 3]], np.int32)
    out, rules, out_shape = down_rulebook(coords, (4, 4, 4))
    assert out_shape == (2, 2, 2)
    for o, k in zip(*np.nonzero(rules < 3), strict=True):
        tap = np.array([k // 9, (k // 3) % 3, k % 3])
        np.testing.assert_array_equal(coords[rules[o, k], 1:], out[o, 1:] * 2 - 1 + tap)
    assert out.tolist() == [[0, 0, 0, 0], [0, 0, 1, 1], [0, 1, 1, 1]]  # worked out by hand
    assert rules[2, 5] == 1 and rules[2, 26] == 2 and (rules[2] < 3).sum() == 2


def test_sparse_wide_row_matches_reference() -> None:
    coords = np.array([[0, 1, 1, 60], [0, 1, 2, 0], [0, 2, 1, 33]], np.int32)  # far apart in x
    out, rules, _ = down_rulebook(coords, (3, 3, 64))
    ref_out, ref_rules, _ = down_rulebook_numpy(coords, (3, 3, 64))
    np.testing.assert_array_equal(out, ref_out)
    np.testing.assert_array_equal(rules, ref_rules)
    row = (out[:, 1] == 1) & (out[:, 2] == 1)
    assert out[row, 3].tolist() == [0, 16, 17, 30]  # one output row, x' ascending


def test_samples_in_a_batch_never_mix() -> None:
    one = np.array([[2, 2, 2], [2, 2, 3], [3, 2, 2]])
    coords = batch_coords([one, one])
    assert coords[:, 0].tolist() == [0, 0, 0, 1, 1, 1]
    rules = subm_rulebook(coords, (5, 5, 5))
    first, second = rules[:3], rules[3:]
    assert np.all((first < 3) | (first == 6)) and np.all((second >= 3) | (second == 6))
    np.testing.assert_array_equal(np.where(second < 6, second - 3, 6), np.where(first < 6, first, 6))
    out, _, _ = down_rulebook(coords, (5, 5, 5))
    assert sorted(set(out[:, 0].tolist())) == [0, 1]


def test_encoder_rulebooks_chain_the_levels() -> None:
    rng = np.random.default_rng(3)
    shape = (10, 40, 40)
    coords = random_coords(rng, shape, 2, 0.05)
    rb = build_encoder_rulebooks(coords, shape, num_down=3)
    assert rb.shapes == ((10, 40, 40), (5, 20, 20), (3, 10, 10), (2, 5, 5))
    assert len(rb.coords) == len(rb.subm) == 4 and len(rb.down) == 3
    for level in range(3):
        out, rules, out_shape = down_rulebook(rb.coords[level], rb.shapes[level])
        np.testing.assert_array_equal(rb.coords[level + 1], out)
        np.testing.assert_array_equal(rb.down[level], rules)
        assert out_shape == rb.shapes[level + 1]
    for level in range(4):
        np.testing.assert_array_equal(rb.subm[level], subm_rulebook(rb.coords[level], rb.shapes[level]))
    np.testing.assert_array_equal(rb.coords[0], coords)


def test_empty_and_bad_input() -> None:
    empty = np.empty((0, 4), np.int32)
    rb = build_encoder_rulebooks(empty, (8, 8, 8))
    assert [c.shape for c in rb.coords] == [(0, 4)] * 4 and rb.subm[0].shape == (0, 27)
    with pytest.raises(ValueError, match="sorted"):
        subm_rulebook(np.array([[0, 0, 0, 1], [0, 0, 0, 0]], np.int32), (2, 2, 2))
    with pytest.raises(ValueError, match="sorted"):
        subm_rulebook(np.array([[0, 0, 0, 1], [0, 0, 0, 1]], np.int32), (2, 2, 2))
    with pytest.raises(ValueError, match="outside"):
        subm_rulebook(np.array([[0, 0, 0, 2]], np.int32), (2, 2, 2))
    with pytest.raises(ValueError, match="outside"):
        subm_rulebook(np.array([[-1, 0, 0, 0]], np.int32), (2, 2, 2))
    with pytest.raises(ValueError, match=r"\(V, 4\)"):
        subm_rulebook(np.zeros((3, 3), np.int32), (2, 2, 2))
    with pytest.raises(ValueError, match="too small"):
        down_rulebook(np.array([[0, 0, 0, 0]], np.int32), (1, 1, 1), stride=1, padding=0)
