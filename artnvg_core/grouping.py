"""Neighbouring-view groups: split capture cameras into balanced groups of nearby views.

ArtNVG stylizes the views of one group jointly (neighbouring-view attention), so a
group should hold views whose camera centres lie close together. ``group_views``
splits the camera centres by balanced k-means:

* number of groups ``G = ceil(C / N)`` for ``C`` views and group size ``N``: the fewest
  groups of at most ``N`` views (the paper's N bounds a group; ``C <= N`` gives one group);
* every view belongs to exactly one group and the group sizes are
  ``floor(C / G)`` or ``ceil(C / G)`` (at most ``N``), so sizes differ by at most one and,
  for ``C >= N``, no group holds fewer than ``ceil(N / 2)`` views: no fragments
  (96 views, N = 15: 7 groups, five of 14 and two of 13);
* ``multiple`` rounds G up to a multiple of it (at most one group per view), the sizes still
  balanced: groups that share ``multiple`` devices evenly (96 views, N = 15, multiple 4: 8 groups
  of 12, where 7 leave one of 4 devices idle for the last round);
* the partition seeks the least within-group sum of squared distances of the
  centres to their group mean (:func:`~artnvg_core.balanced_kmeans.balanced_kmeans` gives
  the method and its cost);
* it is deterministic, and the partition (as a set of sets of view indices) does
  not depend on the order of the input views, as long as camera centres are
  distinct: the work is done in a canonical order (centres sorted by x, y, z).

Optionally each group also borrows ``context`` views: the views of other groups
nearest to it (distance to its closest owned view). A sampler lets them attend as
shared context and discards their outputs.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from .balanced_kmeans import balanced_kmeans
from .cameras import CameraSet
from .counted import counted

CamerasLike = CameraSet | torch.Tensor | np.ndarray  # a CameraSet, or its camera centres [C, 3]

DEFAULT_GROUP_SIZE = 15


@dataclass(frozen=True)
class ViewGroup:
    """One group: ``views`` it owns and ``context`` views it borrows from other groups.

    Both are view indices into the grouped CameraSet, sorted ascending.
    """

    views: tuple[int, ...]
    context: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "views", tuple(int(v) for v in self.views))
        object.__setattr__(self, "context", tuple(int(v) for v in self.context))

    @property
    def all_views(self) -> tuple[int, ...]:
        """Owned views followed by context views (the order a sampler processes them)."""
        return self.views + self.context


@dataclass(frozen=True)
class ViewGroups:
    """A partition of ``num_views`` views into groups (each owned view in exactly one group).

    centers: the camera centre of every view (world units), when known (:func:`group_views` records them).
    """

    groups: tuple[ViewGroup, ...]
    num_views: int
    centers: tuple[tuple[float, float, float], ...] | None = field(default=None, compare=False)
    _owner: tuple[int, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "groups", tuple(self.groups))
        if self.centers is not None:
            centers = _centers_array(np.asarray(self.centers, dtype=np.float64).reshape(-1, 3), "ViewGroups.centers")
            if len(centers) != self.num_views:
                raise ValueError(f"ViewGroups.centers: {counted(len(centers), 'centre')} for "
                                 f"{counted(self.num_views, 'view')}")
            object.__setattr__(self, "centers", tuple(map(tuple, centers.tolist())))
        owner = [-1] * self.num_views
        for g, group in enumerate(self.groups):
            for v in group.views + group.context:
                if not 0 <= v < self.num_views:
                    raise ValueError(f"ViewGroups.groups[{g}]: view {v} out of range for "
                                     f"{counted(self.num_views, 'view')}")
            for v in group.views:
                if owner[v] != -1:
                    raise ValueError(f"ViewGroups.groups[{g}].views: view {v} already owned by group {owner[v]}")
                owner[v] = g
            if len(set(group.context)) != len(group.context) or set(group.views) & set(group.context):
                raise ValueError(f"ViewGroups.groups[{g}].context: expected distinct views the group does not own")
        if -1 in owner:
            raise ValueError(f"ViewGroups.groups: view {owner.index(-1)} belongs to no group")
        object.__setattr__(self, "_owner", tuple(owner))

    def __len__(self) -> int:
        return len(self.groups)

    def __iter__(self) -> Iterator[ViewGroup]:
        return iter(self.groups)

    def __getitem__(self, index: int) -> ViewGroup:
        return self.groups[index]

    def group_of(self, view: int) -> int:
        """Index of the group that owns ``view``."""
        if not 0 <= view < self.num_views:
            raise ValueError(f"ViewGroups.group_of: view {view} out of range for "
                             f"{counted(self.num_views, 'view')}")
        return self._owner[view]

    def as_lists(self) -> list[list[int]]:
        """The owned views of every group, as plain lists."""
        return [list(group.views) for group in self.groups]


def group_views(
    cameras: CamerasLike,
    group_size: int = DEFAULT_GROUP_SIZE,
    *,
    context: int = 0,
    multiple: int = 1,
) -> ViewGroups:
    """Split views into the fewest balanced groups of at most ``group_size`` nearby cameras, their
    number rounded up to a multiple of ``multiple`` (at most one group per view).

    ``cameras`` is a CameraSet or its camera centres ``[C, 3]`` (tensor or array, world units).
    ``context`` views per group are borrowed from other groups (fewer when fewer
    exist). Groups are ordered by their smallest view; views and context views
    within a group ascend. Sizes and guarantees are given in the module docstring.
    """
    if isinstance(group_size, bool) or not isinstance(group_size, int) or group_size < 1:
        raise ValueError(f"group_views: group_size must be an integer >= 1, got {group_size!r}")
    if isinstance(context, bool) or not isinstance(context, int) or context < 0:
        raise ValueError(f"group_views: context must be an integer >= 0, got {context!r}")
    if isinstance(multiple, bool) or not isinstance(multiple, int) or multiple < 1:
        raise ValueError(f"group_views: multiple must be an integer >= 1, got {multiple!r}")
    centers = _centers_array(cameras, "group_views")
    count = len(centers)
    if count == 0:
        raise ValueError("group_views: cameras must hold at least one view, got 0")

    canonical = np.lexsort(centers.T[::-1])  # by x, then y, then z; stable for duplicates
    points = centers[canonical] - centers[canonical].mean(axis=0)
    sizes = balanced_group_sizes(count, group_size, multiple)
    if 1 < len(sizes) < count:
        labels = balanced_kmeans(points, sizes)
    else:  # one group, or one view per group
        labels = np.repeat(np.arange(len(sizes)), sizes)

    members = [np.flatnonzero(labels == g) for g in range(len(sizes))]
    borrowed = [_nearest_outside(points, own, context) for own in members]
    groups = [
        ViewGroup(
            views=tuple(sorted(int(canonical[i]) for i in own)),
            context=tuple(sorted(int(canonical[i]) for i in ctx)),
        )
        for own, ctx in zip(members, borrowed)
    ]
    groups.sort(key=lambda group: group.views[0])
    return ViewGroups(groups=tuple(groups), num_views=count, centers=centers)


def balanced_group_sizes(num_views: int, group_size: int, multiple: int = 1) -> list[int]:
    """Sizes of the ``G = ceil(C / N)`` groups, G rounded up to a multiple of ``multiple`` but at most C
    (each at most N, differing by at most one), larger first, summing to C."""
    fewest = max(1, -(-num_views // group_size))
    num_groups = min(-(-fewest // multiple) * multiple, max(num_views, 1))
    base, extra = divmod(num_views, num_groups)
    return [base + 1] * extra + [base] * (num_groups - extra)


def group_cost(cameras: CamerasLike, groups: ViewGroups | Sequence[Sequence[int]]) -> float:
    """Mean camera-centre distance over all pairs of views owned by the same group.

    ``groups`` is a ViewGroups or lists of view indices; context views are ignored.
    Returns 0.0 when no group holds two views.
    """
    centers = _centers_array(cameras, "group_cost")
    index_lists = groups.as_lists() if isinstance(groups, ViewGroups) else [list(g) for g in groups]
    total, pairs = 0.0, 0
    for g, views in enumerate(index_lists):
        for v in views:
            if not 0 <= v < len(centers):
                raise ValueError(f"group_cost: groups[{g}] has view {v}, out of range for "
                                 f"{counted(len(centers), 'view')}")
        pts = centers[views]
        dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
        total += float(np.triu(dist, k=1).sum())
        pairs += len(views) * (len(views) - 1) // 2
    return total / pairs if pairs else 0.0


def nearest_views(cameras: CamerasLike, k: int) -> tuple[tuple[int, ...], ...]:
    """For each of the C views, the indices of its ``k`` nearest other views by camera-centre
    distance, nearest first (ties: lower index first); ``k`` is capped at C - 1."""
    centers = _centers_array(cameras, "nearest_views")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"nearest_views: k must be an integer >= 1, got {k!r}")
    distances = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    np.fill_diagonal(distances, np.inf)
    order = np.argsort(distances, axis=1, kind="stable")[:, : min(k, len(centers) - 1)]
    return tuple(tuple(int(j) for j in row) for row in order)


def _centers_array(cameras: CamerasLike, caller: str) -> np.ndarray:
    """Camera centres as float64 numpy [C, 3], validated."""
    centers = cameras.centers if isinstance(cameras, CameraSet) else cameras
    if not isinstance(centers, (torch.Tensor, np.ndarray)):
        raise ValueError(
            f"{caller}: cameras must be a CameraSet or a [C, 3] tensor or array of camera centres, "
            f"got {type(cameras).__name__}"
        )
    if isinstance(centers, torch.Tensor):
        centers = centers.detach().cpu().double().numpy()
    centers = np.asarray(centers, dtype=np.float64)
    if centers.ndim != 2 or centers.shape[1] != 3:
        raise ValueError(f"{caller}: camera centres must have shape (C, 3), got {tuple(centers.shape)}")
    if not np.isfinite(centers).all():
        raise ValueError(f"{caller}: camera centres must be finite")
    return centers


def _nearest_outside(points: np.ndarray, own: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` views outside ``own`` nearest to any view of ``own`` (canonical indices)."""
    if count == 0:
        return np.empty(0, dtype=np.int64)
    dist = np.linalg.norm(points[:, None, :] - points[own][None, :, :], axis=-1).min(axis=1)
    dist[own] = np.inf
    available = len(points) - len(own)
    return np.argsort(dist, kind="stable")[: min(count, available)]
