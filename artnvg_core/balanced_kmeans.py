"""Balanced k-means: points split into groups of given sizes, close together.

:func:`balanced_kmeans` solves a size-constrained k-means: every point belongs to exactly one group,
the group sizes are a given multiset (differing by at most one), and the partition seeks the least
within-group sum of squared distances of the points to their group mean. It finds a local optimum,
found to be the global one on small brute-forced sets: starting from a recursive bisection along the
principal axis and from a few seeded k-means++ seedings, it alternates group means with an exact
size-constrained assignment of points to groups (negative-cycle cancelling on the groups' exchange
graph), then exchanges single points between groups while that still helps; the best start wins. The
seedings use a fixed seed, so the same points in the same order give the same labels.

Cost on a CPU: about 0.1 s for 200 points in 3D, a few seconds for 1,000.
"""

from __future__ import annotations

import numpy as np

_KMEANS_PP_STARTS = 8  # seeded k-means++ starts tried besides the principal-axis bisection
_SEED = 0
_MAX_LLOYD_ITERATIONS = 100
_MAX_REFINE_PASSES = 200


def balanced_kmeans(points: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Group labels [P] (0 to G - 1) of ``points`` [P, D] (float64) for ``G = len(sizes)`` groups whose sizes are
    the multiset ``sizes`` (larger first, differing by at most one, summing to P), with a low within-group sum of
    squared distances to the group means: the best of several starts (module docstring). Deterministic for the
    same points in the same order. Centre the points first: the tolerances scale with their sum of squares."""
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
    """Squared distances [P, A] from every point [P, D] to every anchor [A, D]."""
    return ((points[:, None, :] - anchors[None, :, :]) ** 2).sum(-1)


def _group_means(points: np.ndarray, labels: np.ndarray, num_groups: int) -> np.ndarray:
    """Mean point of every group, [G, D] (every group non-empty)."""
    sums = np.zeros((num_groups, points.shape[1]))
    np.add.at(sums, labels, points)
    return sums / np.bincount(labels, minlength=num_groups)[:, None]


def _kmeans_pp_seeds(points: np.ndarray, num_groups: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding: each next seed drawn with probability proportional to its squared
    distance to the nearest seed so far. Returns seed points [G, D]."""
    chosen = [min(int(rng.random() * len(points)), len(points) - 1)]
    nearest = ((points - points[chosen[0]]) ** 2).sum(-1)
    for _ in range(num_groups - 1):
        cumulative = np.cumsum(nearest)
        pick = int(np.searchsorted(cumulative, rng.random() * cumulative[-1], side="right"))
        chosen.append(min(pick, len(points) - 1))
        nearest = np.minimum(nearest, ((points - points[chosen[-1]]) ** 2).sum(-1))
    return points[chosen]


def _greedy_assign(cost: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Feasible labels [P] from costs [P, G]: cheapest (point, group) pairs first, groups
    capped at ``sizes[-1]`` points plus as many one-point extras as ``sizes`` has larger groups."""
    num_points, num_groups = cost.shape
    small = sizes[-1]
    extras = sizes.count(small + 1)
    labels = np.full(num_points, -1)
    counts = np.zeros(num_groups, dtype=np.int64)
    assigned = 0
    for flat in np.argsort(cost, axis=None, kind="stable"):
        point, group = divmod(int(flat), num_groups)
        if labels[point] >= 0 or counts[group] > small:
            continue
        if counts[group] == small:
            if extras == 0:
                continue
            extras -= 1
        labels[point] = group
        counts[group] += 1
        assigned += 1
        if assigned == num_points:
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
    """Labels of least total cost [P, G] among those whose group sizes form the multiset ``sizes``.

    Starting from the feasible ``labels``, cancels negative cycles of the exchange
    graph: edge g -> h weighs the cheapest cost change of moving one point from g to
    h. An extra node with free edges from it to every larger group and from every
    smaller group to it turns a chain of moves from a larger to a smaller group
    (which swaps their sizes) into a cycle too. No negative cycle left = optimal.
    """
    labels = labels.copy()
    num_points, num_groups = cost.shape
    counts = np.bincount(labels, minlength=num_groups)
    change = cost - cost[np.arange(num_points), labels][:, None]  # [P, G]: moving each point to each group
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
        if sum(change[point, target] for point, _, target in moves) >= -tolerance:
            return labels
        for point, source, target in moves:
            labels[point] = target
            counts[source] -= 1
            counts[target] += 1
            change[point] = cost[point] - cost[point, target]
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
    """Initial labels [P]: recursive split along the principal axis into groups of ``sizes``."""
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
    one point of A with one point of another group, or (when A is one larger than a
    group B) a move of one point from A to B, which keeps the multiset of sizes.
    """
    labels = labels.copy()
    counts = np.bincount(labels, minlength=num_groups).astype(np.float64)
    sums = _group_means(points, labels, num_groups) * counts[:, None]
    for _ in range(_MAX_REFINE_PASSES):
        improved = False
        for group in range(num_groups):
            means = sums / counts[:, None]
            own = np.flatnonzero(labels == group)
            delta, point, target, partner = min(
                _best_swap(points, labels, counts, means, group, own),
                _best_move(points, counts, means, group, own),
            )
            if delta >= -tolerance:
                continue
            improved = True
            for moved, source, destination in ((point, group, target), (partner, target, group)):
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
    """Best SSE change (delta, point, its new group, partner point) from swapping a point of
    ``group`` with a point of another group."""
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
    """Best SSE change (delta, point, its new group, -1) from moving a point of ``group`` to a
    group one point smaller; delta is ``inf`` when there is none."""
    targets = np.flatnonzero(counts == counts[group] - 1)
    if len(targets) == 0:
        return np.inf, -1, -1, -1
    removal = counts[group] / (counts[group] - 1) * ((points[own] - means[group]) ** 2).sum(-1)  # [own]
    addition = counts[targets] / (counts[targets] + 1) * _squared_distances(points[own], means[targets])
    delta = addition - removal[:, None]  # [own, targets]
    i, t = np.unravel_index(int(np.argmin(delta)), delta.shape)
    return float(delta[i, t]), int(own[i]), int(targets[t]), -1
