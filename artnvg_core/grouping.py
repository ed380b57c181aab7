"""Neighbouring-view groups: split capture cameras into balanced groups of nearby views.

ArtNVG stylizes the views of one group jointly (neighbouring-view attention), so a
group should hold views whose camera centres lie close together. ``group_views``
solves a size-constrained (balanced) k-means on the camera centres:

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
  centres to their group mean (balanced k-means; a local optimum, found to be the
  global one on small brute-forced sets): starting from a recursive
  bisection along the principal axis and from a few seeded k-means++ seedings, it
  alternates group means with an exact size-constrained assignment of views to
  groups (negative-cycle cancelling on the groups' exchange graph), then exchanges
  single views between groups while that still helps; the best start wins;
* it is deterministic, and the partition (as a set of sets of view indices) does
  not depend on the order of the input views, as long as camera centres are
  distinct: the work is done in a canonical order (centres sorted by x, y, z) and
  the k-means++ seedings use a fixed seed.

Cost on a CPU: about 0.1 s for 200 views, a few seconds for 1,000.

Optionally each group also borrows ``context`` views: the views of other groups
nearest to it (distance to its closest owned view). A sampler lets them attend as
shared context and discards their outputs.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from .cameras import CameraSet

CamerasLike = CameraSet | torch.Tensor | np.ndarray  # a CameraSet, or its camera centres [C, 3]

DEFAULT_GROUP_SIZE = 15
_KMEANS_PP_STARTS = 8  # seeded k-means++ starts tried besides the principal-axis bisection
_SEED = 0
_MAX_LLOYD_ITERATIONS = 100
_MAX_REFINE_PASSES = 200


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
                raise ValueError(f"ViewGroups.centers: {len(centers)} centres for {self.num_views} views")
            object.__setattr__(self, "centers", tuple(map(tuple, centers.tolist())))
        owner = [-1] * self.num_views
        for g, group in enumerate(self.groups):
            for v in group.views + group.context:
                if not 0 <= v < self.num_views:
                    raise ValueError(f"ViewGroups.groups[{g}]: view {v} out of range for {self.num_views} views")
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
            raise ValueError(f"ViewGroups.group_of: view {view} out of range for {self.num_views} views")
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
        labels = _balanced_kmeans(points, sizes)
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
                raise ValueError(f"group_cost: groups[{g}] has view {v}, out of range for {len(centers)} views")
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


def _balanced_kmeans(points: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Group labels [C] with group sizes ``sizes`` and a low within-group SSE (best of several starts)."""
    num_groups = len(sizes)
    tolerance = 1e-12 * max(float((points**2).sum()), np.finfo(np.float64).tiny)
    starts = [_bisect(points, sizes)]
    rng = np.random.default_rng(_SEED)
    for _ in range(_KMEANS_PP_STARTS):
        seeds = _kmeans_pp_seeds(points, num_groups, rng)
        starts.append(_greedy_assign(_squared_distances(points, seeds), sizes))
    best_labels, best_sse = starts[0], np.inf
    for labels in starts:
        labels = _lloyd(points, labels, sizes, tolerance)
        labels = _refine(points, labels, num_groups, tolerance)
        sse = float(((points - _group_means(points, labels, num_groups)[labels]) ** 2).sum())
        if sse < best_sse - tolerance:
            best_labels, best_sse = labels, sse
    return best_labels


def _squared_distances(points: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """Squared distances [P, A] from every point [P, 3] to every anchor [A, 3]."""
    return ((points[:, None, :] - anchors[None, :, :]) ** 2).sum(-1)


def _group_means(points: np.ndarray, labels: np.ndarray, num_groups: int) -> np.ndarray:
    """Mean point of every group, [G, 3] (every group non-empty)."""
    sums = np.zeros((num_groups, points.shape[1]))
    np.add.at(sums, labels, points)
    return sums / np.bincount(labels, minlength=num_groups)[:, None]


def _kmeans_pp_seeds(points: np.ndarray, num_groups: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding: each next seed drawn with probability proportional to its squared
    distance to the nearest seed so far. Returns seed points [G, 3]."""
    chosen = [min(int(rng.random() * len(points)), len(points) - 1)]
    nearest = ((points - points[chosen[0]]) ** 2).sum(-1)
    for _ in range(num_groups - 1):
        cumulative = np.cumsum(nearest)
        pick = int(np.searchsorted(cumulative, rng.random() * cumulative[-1], side="right"))
        chosen.append(min(pick, len(points) - 1))
        nearest = np.minimum(nearest, ((points - points[chosen[-1]]) ** 2).sum(-1))
    return points[chosen]


def _greedy_assign(cost: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Feasible labels [C] from costs [C, G]: cheapest (view, group) pairs first, groups
    capped at ``sizes[-1]`` views plus as many one-view extras as ``sizes`` has larger groups."""
    num_views, num_groups = cost.shape
    small = sizes[-1]
    extras = sizes.count(small + 1)
    labels = np.full(num_views, -1)
    counts = np.zeros(num_groups, dtype=np.int64)
    assigned = 0
    for flat in np.argsort(cost, axis=None, kind="stable"):
        view, group = divmod(int(flat), num_groups)
        if labels[view] >= 0 or counts[group] > small:
            continue
        if counts[group] == small:
            if extras == 0:
                continue
            extras -= 1
        labels[view] = group
        counts[group] += 1
        assigned += 1
        if assigned == num_views:
            break
    return labels


def _lloyd(points: np.ndarray, labels: np.ndarray, sizes: list[int], tolerance: float) -> np.ndarray:
    """Alternate group means and the optimal size-constrained assignment to them until stable."""
    for _ in range(_MAX_LLOYD_ITERATIONS):
        means = _group_means(points, labels, len(sizes))
        new_labels = _balanced_assign(_squared_distances(points, means), labels, sizes, tolerance)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
    return labels


def _balanced_assign(cost: np.ndarray, labels: np.ndarray, sizes: list[int], tolerance: float) -> np.ndarray:
    """Labels of least total cost [C, G] among those whose group sizes form the multiset ``sizes``.

    Starting from the feasible ``labels``, cancels negative cycles of the exchange
    graph: edge g -> h weighs the cheapest cost change of moving one view from g to
    h. An extra node with free edges from it to every larger group and from every
    smaller group to it turns a chain of moves from a larger to a smaller group
    (which swaps their sizes) into a cycle too. No negative cycle left = optimal.
    """
    labels = labels.copy()
    num_views, num_groups = cost.shape
    counts = np.bincount(labels, minlength=num_groups)
    change = cost - cost[np.arange(num_views), labels][:, None]  # [C, G]: moving each view to each group
    weights = np.full((num_groups + 1, num_groups + 1), np.inf)  # node num_groups: the extra node

    def update_edges(groups) -> None:
        for group in groups:
            weights[group, :num_groups] = change[labels == group].min(axis=0)
            weights[group, group] = np.inf

    update_edges(range(num_groups))
    while True:
        if sizes[0] != sizes[-1]:
            weights[num_groups, :num_groups] = np.where(counts == sizes[0], 0.0, np.inf)
            weights[:num_groups, num_groups] = np.where(counts == sizes[-1], 0.0, np.inf)
        cycle = _negative_cycle(weights, tolerance)
        if cycle is None:
            return labels
        moves = []
        for source, target in cycle:
            if source < num_groups and target < num_groups:
                members = np.flatnonzero(labels == source)
                moves.append((int(members[np.argmin(change[members, target])]), source, target))
        if sum(change[view, target] for view, _, target in moves) >= -tolerance:
            return labels
        for view, source, target in moves:
            labels[view] = target
            counts[source] -= 1
            counts[target] += 1
            change[view] = cost[view] - cost[view, target]
        update_edges({group for move in moves for group in move[1:]})


def _negative_cycle(weights: np.ndarray, tolerance: float) -> list[tuple[int, int]] | None:
    """Edges (source, target) of a negative cycle of the dense graph ``weights`` [n, n], or None.

    Bellman-Ford from a virtual source joined to every node; any cycle of the
    predecessor graph is negative, so it is checked for one after every round.
    Gives up (None) after 3n rounds without one: the caller then keeps a valid
    but not proven optimal assignment.
    """
    size = len(weights)
    dist = np.zeros(size)
    pred = np.full(size, -1)
    for _ in range(3 * size):
        candidates = dist[:, None] + weights
        best = candidates.argmin(axis=0)
        value = candidates[best, np.arange(size)]
        improved = value < dist - tolerance
        if not improved.any():
            return None
        dist = np.where(improved, value, dist)
        pred = np.where(improved, best, pred)
        cycle = _predecessor_cycle(pred)
        if cycle is not None:
            return cycle
    return None


def _predecessor_cycle(pred: np.ndarray) -> list[tuple[int, int]] | None:
    """Edges (pred[v], v) of one cycle of the predecessor graph (-1 = no predecessor), or None."""
    parent = pred.tolist()
    state = [0] * len(parent)  # 0 unseen, 1 on the current walk, 2 done
    for start in range(len(parent)):
        walk, node = [], start
        while node >= 0 and state[node] == 0:
            state[node] = 1
            walk.append(node)
            node = parent[node]
        if node >= 0 and state[node] == 1:
            return [(parent[v], v) for v in walk[walk.index(node):]]
        for v in walk:
            state[v] = 2
    return None


def _bisect(points: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Initial labels [C]: recursive split along the principal axis into groups of ``sizes``."""
    labels = np.empty(len(points), dtype=np.int64)

    def split(indices: np.ndarray, first_label: int, part_sizes: list[int]) -> None:
        if len(part_sizes) == 1:
            labels[indices] = first_label
            return
        half = len(part_sizes) // 2
        pts = points[indices] - points[indices].mean(axis=0)
        _, vectors = np.linalg.eigh(pts.T @ pts)
        order = indices[np.argsort(pts @ vectors[:, -1], kind="stable")]
        cut = sum(part_sizes[:half])
        split(order[:cut], first_label, part_sizes[:half])
        split(order[cut:], first_label + half, part_sizes[half:])

    split(np.arange(len(points)), 0, sizes)
    return labels


def _refine(points: np.ndarray, labels: np.ndarray, num_groups: int, tolerance: float) -> np.ndarray:
    """Lower the within-group sum of squared distances to the group means, sizes kept.

    Each pass visits every group A and applies its best improving step: a swap of
    one view of A with one view of another group, or (when A is one larger than a
    group B) a move of one view from A to B, which keeps the multiset of sizes.
    """
    labels = labels.copy()
    counts = np.bincount(labels, minlength=num_groups).astype(np.float64)
    sums = _group_means(points, labels, num_groups) * counts[:, None]
    for _ in range(_MAX_REFINE_PASSES):
        improved = False
        for group in range(num_groups):
            means = sums / counts[:, None]
            own = np.flatnonzero(labels == group)
            delta, view, target, partner = min(
                _best_swap(points, labels, counts, means, group, own),
                _best_move(points, counts, means, group, own),
            )
            if delta >= -tolerance:
                continue
            improved = True
            for moved, source, destination in ((view, group, target), (partner, target, group)):
                if moved >= 0:
                    labels[moved] = destination
                    sums[source] -= points[moved]
                    sums[destination] += points[moved]
                    counts[source] -= 1
                    counts[destination] += 1
        if not improved:
            break
    return labels


def _best_swap(
    points: np.ndarray, labels: np.ndarray, counts: np.ndarray, means: np.ndarray, group: int, own: np.ndarray
) -> tuple[float, int, int, int]:
    """Best SSE change (delta, view, its new group, partner view) from swapping a view of
    ``group`` with a view of another group."""
    other = np.flatnonzero(labels != group)
    offset = points[other][None, :, :] - points[own][:, None, :]  # [own, other, 3]
    other_groups = labels[other]
    delta = -2.0 * np.einsum("ijk,jk->ij", offset, means[group] - means[other_groups]) - (offset**2).sum(-1) * (
        1.0 / counts[group] + 1.0 / counts[other_groups]
    )
    i, j = np.unravel_index(int(np.argmin(delta)), delta.shape)
    return float(delta[i, j]), int(own[i]), int(other_groups[j]), int(other[j])


def _best_move(
    points: np.ndarray, counts: np.ndarray, means: np.ndarray, group: int, own: np.ndarray
) -> tuple[float, int, int, int]:
    """Best SSE change (delta, view, its new group, -1) from moving a view of ``group`` to a
    group one view smaller; delta is ``inf`` when there is none."""
    targets = np.flatnonzero(counts == counts[group] - 1)
    if len(targets) == 0:
        return np.inf, -1, -1, -1
    removal = counts[group] / (counts[group] - 1) * ((points[own] - means[group]) ** 2).sum(-1)  # [own]
    addition = counts[targets] / (counts[targets] + 1) * _squared_distances(points[own], means[targets])
    delta = addition - removal[:, None]  # [own, targets]
    i, t = np.unravel_index(int(np.argmin(delta)), delta.shape)
    return float(delta[i, t]), int(own[i]), int(targets[t]), -1


def _nearest_outside(points: np.ndarray, own: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` views outside ``own`` nearest to any view of ``own`` (canonical indices)."""
    if count == 0:
        return np.empty(0, dtype=np.int64)
    dist = np.linalg.norm(points[:, None, :] - points[own][None, :, :], axis=-1).min(axis=1)
    dist[own] = np.inf
    available = len(points) - len(own)
    return np.argsort(dist, kind="stable")[: min(count, available)]
