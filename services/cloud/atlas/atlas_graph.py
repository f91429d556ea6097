"""The atlas's covisibility graph and spanning tree over keyframe keys (ORB-SLAM).

The weight between two keyframes is the number of map points both observe; the atlas adds
and removes weight as it links and unlinks observations, in any order. The spanning tree
attaches every keyframe to its strongest covisible keyframe already in the tree; each agent's
first keyframe is a root (parent -1). Removing a keyframe re-attaches its children to its
parent (or makes them roots). Owned and mutated by :class:`~services.cloud.atlas.atlas.Atlas` only.
"""

from __future__ import annotations


class CovisibilityGraph:
    """Covisibility weights and spanning-tree parents of an atlas's keyframes, by key."""

    def __init__(self) -> None:
        self._weights: dict[int, dict[int, int]] = {}  # key -> {other key: shared points}
        self._parent: dict[int, int] = {}  # child -> parent; roots map to -1

    def add_keyframe(self, key: int, root: bool) -> None:
        """A new keyframe without covisibility; ``root``: it starts its own tree."""
        self._weights[key] = {}
        if root:
            self._parent[key] = -1

    def add_weight(self, a: int, b: int, w: int) -> None:
        """Add ``w`` (negative: remove) to the weight between ``a`` and ``b``; an edge whose
        weight drops to 0 goes."""
        if a == b:
            return
        ca, cb = self._weights[a], self._weights[b]
        na = ca.get(b, 0) + w
        if na <= 0:
            ca.pop(b, None)
            cb.pop(a, None)
        else:
            ca[b] = na
            cb[a] = na

    def is_attached(self, key: int) -> bool:
        return key in self._parent

    def attach(self, key: int) -> None:
        """Attach ``key`` (and, transitively, waiting neighbours) to the spanning tree."""
        stack = [key]
        while stack:
            k = stack.pop()
            if k in self._parent:
                continue
            in_tree = [(w, o) for o, w in self._weights[k].items() if o in self._parent]
            if not in_tree:
                continue
            self._parent[k] = max(in_tree)[1]
            stack.extend(o for o in self._weights[k] if o not in self._parent)

    def covisible(self, key: int, min_weight: int = 1) -> list[tuple[int, int]]:
        """``[(keyframe key, weight)]`` sorted by decreasing weight (then key)."""
        items = [(o, w) for o, w in self._weights[key].items() if w >= min_weight]
        return sorted(items, key=lambda t: (-t[1], t[0]))

    def parent(self, key: int) -> int | None:
        """Parent in the spanning tree, -1 for a root, None if not attached yet."""
        return self._parent.get(key)

    def remove_keyframe(self, key: int) -> None:
        """Drop ``key``'s edges; its children are re-attached to its parent (or become roots)."""
        parent = self._parent.pop(key, None)
        for child, p in list(self._parent.items()):
            if p == key:
                self._parent[child] = -1 if parent is None else parent
        for other in list(self._weights[key]):
            self._weights[other].pop(key, None)
        del self._weights[key]

    def edges(self) -> list[tuple[int, int, int]]:
        """Every covisibility edge once, ``(a, b, weight)`` with ``a < b``, sorted."""
        return sorted((a, b, w) for a, d in self._weights.items() for b, w in d.items() if a < b)

    def tree(self) -> list[tuple[int, int]]:
        """Spanning-tree edges ``(child, parent)`` (roots left out), sorted."""
        return sorted((c, p) for c, p in self._parent.items() if p >= 0)
