"""Tests of artnvg_core.balanced_kmeans: points split into groups of given sizes, close together."""

import itertools

import numpy as np
import pytest

from artnvg_core.balanced_kmeans import balanced_kmeans


def _within_sse(points: np.ndarray, groups) -> float:
    return sum(float(((points[list(g)] - points[list(g)].mean(0)) ** 2).sum()) for g in groups)


def _groups(labels: np.ndarray, num_groups: int) -> list[list[int]]:
    return [np.flatnonzero(labels == g).tolist() for g in range(num_groups)]


def _balanced_partitions(items: list[int], sizes: list[int]):
    """Every partition of ``items`` into groups of the multiset ``sizes``, each once."""
    if not sizes:
        yield []
        return
    for size in sorted(set(sizes)):
        rest_sizes = list(sizes)
        rest_sizes.remove(size)
        for others in itertools.combinations(items[1:], size - 1):
            group = (items[0], *others)
            rest = [i for i in items if i not in group]
            for partition in _balanced_partitions(rest, rest_sizes):
                yield [group, *partition]


@pytest.mark.parametrize("sizes", [[14] * 5 + [13] * 2, [12] * 8, [2] * 3 + [1], [1] * 6])
def test_labels_give_every_group_its_size_and_repeat(sizes):
    points = np.random.default_rng(len(sizes)).normal(size=(sum(sizes), 3))
    labels = balanced_kmeans(points, sizes)
    assert sorted(np.bincount(labels, minlength=len(sizes)).tolist()) == sorted(sizes)
    assert np.array_equal(balanced_kmeans(points, sizes), labels)


@pytest.mark.parametrize("sizes", [[2, 2, 2, 1], [4, 4], [3, 3, 3], [4, 3, 3]])
def test_matches_brute_force_optimum_on_small_sets(sizes):
    for seed in range(3):
        points = np.random.default_rng(100 + seed).normal(size=(sum(sizes), 3))
        points -= points.mean(axis=0)
        optimum = min(_within_sse(points, p) for p in _balanced_partitions(list(range(len(points))), sizes))
        found = _groups(balanced_kmeans(points, sizes), len(sizes))
        assert _within_sse(points, found) == pytest.approx(optimum, rel=1e-9)


@pytest.mark.parametrize("blob_sizes", [[15] * 6, [15, 15, 15, 14, 14, 14]])
def test_recovers_well_separated_clusters(blob_sizes):
    rng = np.random.default_rng(3)
    anchors = rng.normal(size=(len(blob_sizes), 3)) * 100
    blobs = np.repeat(np.arange(len(blob_sizes)), blob_sizes)
    points = anchors[blobs] + rng.uniform(-1, 1, size=(len(blobs), 3))
    order = rng.permutation(len(blobs))  # unordered input
    points = points[order] - points.mean(axis=0)
    found = {frozenset(g) for g in _groups(balanced_kmeans(points, blob_sizes), len(blob_sizes))}
    assert found == {frozenset(np.flatnonzero(blobs[order] == b).tolist()) for b in range(len(blob_sizes))}
