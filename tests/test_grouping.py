"""Tests of artnvg_core.grouping: balanced neighbouring-view groups."""

import itertools
import heapq
import math
from fractions import Fraction

import numpy as np
import pytest
import torch

from artnvg_core.cameras import CameraSet, load_nerfstudio, look_at
from artnvg_core.grouping import (
    ViewGroup,
    ViewGroups,
    balanced_group_sizes,
    group_cost,
    group_views,
    nearest_views,
)

VIEW_COUNTS = [1, 2, 14, 15, 16, 29, 31, 96, 185]


def _camera_set(centres: torch.Tensor, target=(0.0, 0.0, -50.0)) -> CameraSet:
    """Cameras at ``centres`` [C, 3] all looking at ``target`` (float64, dummy intrinsics)."""
    centres = centres.double()
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    world_to_cam = look_at(centres, torch.tensor(target, dtype=torch.float64), up)
    intrinsics = torch.eye(3, dtype=torch.float64).expand(len(centres), 3, 3).clone()
    return CameraSet(world_to_cam, intrinsics, 64, 64, [f"v{i}" for i in range(len(centres))])


def _orbit(count: int) -> torch.Tensor:
    angle = torch.arange(count, dtype=torch.float64) * (2 * math.pi / count)
    return torch.stack([4 * torch.cos(angle), 4 * torch.sin(angle), torch.ones(count, dtype=torch.float64)], dim=1)


def _forward_facing(count: int) -> torch.Tensor:
    """A row-major grid on the plane z = 0 with 5 cm spacing (first ``count`` points)."""
    side = math.ceil(math.sqrt(count))
    rows, cols = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    grid = torch.stack([cols.flatten() * 0.05, rows.flatten() * 0.05, torch.zeros(side * side)], dim=1)
    return grid[:count].double()


def _unordered(count: int) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(count).normal(size=(count, 3)))


SHAPES = {"orbit": _orbit, "forward_facing": _forward_facing, "unordered": _unordered}


def _within_sse(centres: np.ndarray, groups) -> float:
    return sum(float(((centres[list(g)] - centres[list(g)].mean(0)) ** 2).sum()) for g in groups)


def _mean_pairwise_distance(centres: np.ndarray) -> float:
    """Mean distance over all pairs: the expected group_cost of a random partition."""
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    return float(dist[np.triu_indices(len(centres), k=1)].mean())


def _partition_sets(groups: ViewGroups, relabel=None) -> set:
    relabel = relabel if relabel is not None else list(range(groups.num_views))
    return {(frozenset(relabel[v] for v in g.views), frozenset(relabel[v] for v in g.context)) for g in groups}


@pytest.mark.parametrize("count", VIEW_COUNTS)
@pytest.mark.parametrize("shape", SHAPES)
def test_partition_and_size_bounds(shape, count):
    cameras = _camera_set(SHAPES[shape](count))
    groups = group_views(cameras, 15)

    num_groups = math.ceil(count / 15)
    assert len(groups) == num_groups == len(groups.groups)
    owned = [v for g in groups for v in g.views]
    assert sorted(owned) == list(range(count))  # every view exactly once
    for index, group in enumerate(groups):
        assert list(group.views) == sorted(group.views)
        assert group.context == () and group.all_views == group.views
        assert len(group.views) in (count // num_groups, -(-count // num_groups))
        assert len(group.views) <= 15
        if count >= 15:
            assert len(group.views) >= 8
        assert all(groups.group_of(v) == index for v in group.views)
    assert groups.as_lists() == [list(g.views) for g in groups]


def test_balanced_group_sizes_bounds_exhaustive():
    for group_size in range(1, 31):
        for count in range(1, 241):
            sizes = balanced_group_sizes(count, group_size)
            num_groups = len(sizes)
            assert sum(sizes) == count and max(sizes) - min(sizes) <= 1
            assert sizes == sorted(sizes, reverse=True)
            # G is the fewest groups of at most N views: G - 1 groups could not hold C views.
            assert max(sizes) <= group_size and (num_groups - 1) * group_size < count
            if count >= group_size:  # no fragments
                assert min(sizes) >= Fraction(group_size, 2)


def test_group_count_rounded_to_a_multiple_exhaustive():
    for multiple in (1, 2, 3, 4, 8):
        for group_size in range(1, 21):
            for count in range(1, 121):
                sizes = balanced_group_sizes(count, group_size, multiple)
                fewest = len(balanced_group_sizes(count, group_size))
                assert sum(sizes) == count and max(sizes) - min(sizes) <= 1 and max(sizes) <= group_size
                assert sizes == sorted(sizes, reverse=True)
                # the smallest multiple of `multiple` that is at least the fewest groups, or one group per view
                expected = min(next(g for g in range(fewest, fewest + multiple) if g % multiple == 0), count)
                assert len(sizes) == expected


def _finish_times(durations: list[float], workers: int) -> list[float]:
    """When each worker ends if the durations are handed out largest first, each to the worker free
    first (lowest index on a tie), as GroupExecutor's dispatch does."""
    free = [(0.0, worker) for worker in range(workers)]
    for duration in sorted(durations, reverse=True):
        start, worker = heapq.heappop(free)
        heapq.heappush(free, (start + duration, worker))
    return [end for end, _ in sorted(free, key=lambda item: item[1])]


@pytest.mark.parametrize("workers", [2, 3, 4, 8])
def test_groups_a_multiple_of_the_workers_leave_none_idle_on_a_tail(workers):
    """Fake durations growing with a group's size (attention: faster than linearly): with the group count a
    multiple of the workers, every worker ends within one view's cost of the last (so the makespan is the
    average within that); with the fewest groups a worker can wait a whole group."""
    cost = lambda size: size ** 1.5  # noqa: E731
    waits_a_group = 0
    for count in range(15 * workers, 300, 7):
        sizes = balanced_group_sizes(count, 15, workers)
        ends = _finish_times([cost(size) for size in sizes], workers)
        assert max(ends) - min(ends) <= cost(max(sizes)) - cost(min(sizes)) + 1e-9, (count, sizes)
        assert max(ends) <= sum(map(cost, sizes)) / workers + cost(max(sizes)) - cost(min(sizes)) + 1e-9
        fewest = balanced_group_sizes(count, 15)
        ends = _finish_times([cost(size) for size in fewest], workers)
        waits_a_group += max(ends) - min(ends) >= cost(min(fewest))
    assert waits_a_group  # the default grouping does leave workers idle for a group's time


def test_groups_for_four_devices_on_the_bear_orbit():
    cameras = _orbit(96)
    groups = group_views(cameras, 15, multiple=4)
    assert [len(g.views) for g in groups] == [12] * 8
    assert sorted(v for g in groups for v in g.views) == list(range(96))
    assert len(group_views(cameras, 15)) == 7  # the default stays the fewest groups
    assert len(group_views(cameras, 15, multiple=1)) == 7


@pytest.mark.parametrize("shape", SHAPES)
def test_deterministic_and_invariant_to_input_order(shape):
    cameras = _camera_set(SHAPES[shape](96))
    first = group_views(cameras, 15, context=3)
    assert group_views(cameras, 15, context=3) == first

    perm = np.random.default_rng(7).permutation(96)
    permuted = group_views(cameras.subset(perm.tolist()), 15, context=3)
    # Permuted view i is original view perm[i]: same partition and context up to relabelling.
    assert _partition_sets(permuted, relabel=perm.tolist()) == _partition_sets(first)


def test_camera_set_and_centre_tensor_give_the_same_groups():
    cameras = _camera_set(_unordered(40))
    assert group_views(cameras, 8, context=2) == group_views(cameras.centers, 8, context=2)


@pytest.mark.parametrize("count", [1, 2, 7, 14])
def test_fewer_views_than_group_size_give_one_group(count):
    groups = group_views(_camera_set(_orbit(count)), 15, context=5)
    assert groups.groups == (ViewGroup(views=tuple(range(count)), context=()),)


def test_one_view_per_group():
    groups = group_views(_camera_set(_unordered(6)), 1)
    assert [g.views for g in groups] == [(v,) for v in range(6)]
    assert group_cost(_unordered(6), groups) == 0.0


@pytest.mark.parametrize("copies", [40, 5])
def test_coincident_camera_centres(copies):
    """Panorama rigs (one centre for all views) and repeated positions still give balanced partitions."""
    centres = torch.from_numpy(np.repeat(np.random.default_rng(0).normal(size=(40 // copies, 3)), copies, axis=0))
    groups = group_views(centres, 15, context=2)
    assert sorted(v for g in groups for v in g.views) == list(range(40))
    assert sorted(len(g.views) for g in groups) == [13, 13, 14]
    assert all(len(g.context) == 2 and not set(g.context) & set(g.views) for g in groups)


@pytest.mark.parametrize(("scale", "offset"), [(1e-4, (1000.0, -2000.0, 500.0)), (1e3, (0.0, 0.0, 0.0))])
def test_scale_and_offset_do_not_change_the_grouping_quality(scale, offset):
    """Forward-facing rig moved far away and shrunk to a fraction of a millimetre, or blown up."""
    grid = _forward_facing(96)
    moved = grid * scale + torch.tensor(offset, dtype=torch.float64)
    groups = group_views(moved, 15)
    assert sorted(len(g.views) for g in groups) == [13] * 2 + [14] * 5
    reference = group_views(grid, 15)
    assert _within_sse(grid.numpy(), groups.as_lists()) == pytest.approx(
        _within_sse(grid.numpy(), reference.as_lists()), rel=1e-6
    )


@pytest.mark.parametrize("scene", ["garden", "bear"])
def test_real_scene_groups_far_tighter_than_random(shared_data, scene):
    cameras = load_nerfstudio(shared_data / "scenes" / scene / "transforms.json")
    groups = group_views(cameras, 15)
    cost = group_cost(cameras, groups)
    assert cost < 0.5 * _mean_pairwise_distance(cameras.centers.double().numpy())
    shuffled = np.random.default_rng(0).permutation(len(cameras))
    random_groups = np.split(shuffled, np.cumsum([len(g.views) for g in groups])[:-1])
    assert cost < 0.5 * group_cost(cameras, [g.tolist() for g in random_groups])


def test_group_cost_matches_brute_force():
    centres = np.random.default_rng(5).normal(size=(9, 3))
    lists = [[0, 4, 8], [1, 2], [3], [5, 6, 7]]
    pairs = [(i, j) for g in lists for i, j in itertools.combinations(g, 2)]
    expected = sum(math.dist(centres[i], centres[j]) for i, j in pairs) / len(pairs)
    assert group_cost(torch.from_numpy(centres), lists) == pytest.approx(expected, rel=1e-12)
    with_context = ViewGroups(tuple(ViewGroup(tuple(g), context=(3,) if 3 not in g else ()) for g in lists), 9)
    assert group_cost(torch.from_numpy(centres), with_context) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("context", [1, 4])
def test_context_views_are_nearest_views_of_other_groups(shared_data, context):
    cameras = load_nerfstudio(shared_data / "scenes" / "garden" / "transforms.json")
    centres = cameras.centers.double().numpy()
    groups = group_views(cameras, 15, context=context)
    assert [g.views for g in groups] == [g.views for g in group_views(cameras, 15)]  # context leaves owners alone
    for group in groups:
        assert len(group.context) == context and list(group.context) == sorted(group.context)
        assert not set(group.context) & set(group.views)
        assert group.all_views == group.views + group.context
        others = np.setdiff1d(np.arange(len(centres)), group.views)
        distance = np.linalg.norm(centres[others, None] - centres[None, list(group.views)], axis=-1).min(axis=1)
        chosen = np.isin(others, group.context)
        assert distance[~chosen].min() >= distance[chosen].max()


def test_context_is_capped_by_the_views_of_other_groups():
    groups = group_views(_camera_set(_orbit(16)), 8, context=20)
    assert len(groups) == 2
    for group in groups:
        assert sorted(group.context) == sorted(set(range(16)) - set(group.views))


@pytest.mark.parametrize(
    ("cameras", "kwargs", "message"),
    [
        (_camera_set(_unordered(0)), {}, "at least one view"),
        (_orbit(5), {"group_size": 0}, "group_size"),
        (_orbit(5), {"group_size": 2.5}, "group_size"),
        (_orbit(5), {"group_size": True}, "group_size"),
        (_orbit(5), {"context": -1}, "context"),
        (_orbit(5), {"multiple": 0}, "multiple"),
        (_orbit(5), {"multiple": True}, "multiple"),
        (_orbit(5)[:, :2], {}, r"shape \(C, 3\)"),
        (torch.tensor([[0.0, 0.0, float("nan")]]), {}, "finite"),
        ([[0.0, 0.0, 0.0]], {}, "CameraSet or a \\[C, 3\\] tensor or array"),
    ],
)
def test_rejects_bad_input(cameras, kwargs, message):
    with pytest.raises(ValueError, match=message):
        group_views(cameras, **kwargs)


def test_view_groups_validates_partition():
    with pytest.raises(ValueError, match="already owned"):
        ViewGroups((ViewGroup((0, 1)), ViewGroup((1, 2))), 3)
    with pytest.raises(ValueError, match="belongs to no group"):
        ViewGroups((ViewGroup((0, 2)),), 3)
    with pytest.raises(ValueError, match="out of range"):
        ViewGroups((ViewGroup((0, 1, 2, 3)),), 3)
    with pytest.raises(ValueError, match=r"groups\[0\]\.context"):
        ViewGroups((ViewGroup((0, 1), context=(1,)), ViewGroup((2,))), 3)
    with pytest.raises(ValueError, match=r"groups\[1\]\.context"):
        ViewGroups((ViewGroup((0, 1)), ViewGroup((2,), context=(0, 0))), 3)
    assert ViewGroups([ViewGroup([0, 2], context=[1]), ViewGroup(np.array([1]))], 3) == ViewGroups(
        (ViewGroup((0, 2), (1,)), ViewGroup((1,))), 3
    )
    groups = ViewGroups((ViewGroup((0, 2)), ViewGroup((1,))), 3)
    assert [groups.group_of(v) for v in range(3)] == [0, 1, 0]
    with pytest.raises(ValueError, match="out of range"):
        groups.group_of(3)
    with pytest.raises(ValueError, match="group_cost: groups\\[1\\]"):
        group_cost(_orbit(3), [[0, 1], [5]])


def test_nearest_views_brute_force_and_ties():
    rng = np.random.default_rng(4)
    centers = rng.normal(size=(9, 3))
    for k in (1, 3, 8, 20):
        rows = nearest_views(centers, k)
        for i, row in enumerate(rows):
            others = sorted((float(np.linalg.norm(centers[j] - centers[i])), j) for j in range(9) if j != i)
            assert list(row) == [j for _, j in others[: min(k, 8)]]
    assert nearest_views(np.array([[0.0, 0, 0], [1, 0, 0], [-1, 0, 0]]), 1) == ((1,), (0,), (0,))  # tie: lower index
    with pytest.raises(ValueError, match="k must be an integer >= 1"):
        nearest_views(centers, 0)


def test_groups_record_camera_centres():
    centers = np.random.default_rng(5).normal(size=(12, 3))
    groups = group_views(centers, 4)
    np.testing.assert_array_equal(np.array(groups.centers), centers)
    assert groups == ViewGroups(groups.groups, 12)  # centres do not take part in equality
    with pytest.raises(ValueError, match="ViewGroups.centers: 2 centres for 12 views"):
        ViewGroups(groups.groups, 12, centers=centers[:2])
