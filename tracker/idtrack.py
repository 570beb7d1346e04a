"""IDTrack: the paper's Algorithm 1, exactly.

A single k-d tree (``scipy.spatial.cKDTree``) of the last centroid of every robot ever
seen. For each detected centroid, in order: the first one of an empty tree becomes robot
``nextID``; otherwise its nearest neighbour in the tree is searched; farther than
``sigma`` (the chassis width) it is a new robot (``nextID += 1``), else it overwrites that
node. Nodes are never deleted. The tree is rebuilt after every change, so the next
centroid of the same time step sees it (cKDTree is static). Distances are in the units of
the observations (the pipeline gives arena metres and ``sigma`` converted from the
paper's 100 px).

The paper's heading association (nearest ON and OFF cluster centroids to each full
centroid) is done by :class:`tracker.detect.PaperDetector`, whose detections carry it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from tracker.objects import CONFIRMED, Observation, TrackedRobot

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = ["IDTrack"]


def _kd_tree(xy: np.ndarray) -> cKDTree:
    """``scipy.spatial.cKDTree(xy)``, imported on the first tree: scipy.spatial costs ~0.4 s of CPU
    to import on the 2-core VM at load ~8 (issue 22: start-up of ``arena track``, whose default
    tracker does not use it)."""
    from scipy.spatial import cKDTree

    return cKDTree(xy)


class IDTrack:
    """The paper's IDTrack. ``sigma``: new-robot distance, same units as the observations."""

    def __init__(self, sigma: float) -> None:
        if not (sigma > 0 and math.isfinite(sigma)):
            raise ValueError(f"sigma must be a positive distance, got {sigma!r}")
        self.sigma = float(sigma)
        self.next_id = 1
        self._xy = np.empty((0, 2))
        self._ids: list[int] = []
        self._tree: cKDTree | None = None
        self._age: list[int] = []
        self._hits: list[int] = []

    @property
    def nodes(self) -> dict[int, tuple[float, float]]:
        """All nodes ever created: id -> last (x, y)."""
        return {i: (float(p[0]), float(p[1])) for i, p in zip(self._ids, self._xy)}

    def update(self, observations: list[Observation], t_us: int) -> list[TrackedRobot]:
        """Run one time step; returns one track per observation (the node it updated or created)."""
        out = []
        for ob in observations:
            c = np.array([ob.x, ob.y], dtype=float)
            if self._tree is None:
                node = self._add(c)
            else:
                d, i = self._tree.query(c)
                if d > self.sigma:
                    node = self._add(c)
                else:
                    node = int(i)
                    self._xy[node] = c
                    self._tree = _kd_tree(self._xy)
            self._hits[node] += 1
            out.append(TrackedRobot(track_id=self._ids[node], x=ob.x, y=ob.y, t_us=int(ob.t_us),
                                    yaw=ob.yaw, state=CONFIRMED, hits=self._hits[node],
                                    u=ob.u, v=ob.v, n_events=ob.n_events))
        for k in range(len(self._ids)):
            self._age[k] += 1
        for tr in out:
            tr.age = self._age[self._ids.index(tr.track_id)]
        return out

    def _add(self, c: np.ndarray) -> int:
        self._xy = np.vstack([self._xy, c[None, :]])
        self._ids.append(self.next_id)
        self._age.append(0)
        self._hits.append(0)
        self.next_id += 1
        self._tree = _kd_tree(self._xy)
        return len(self._ids) - 1
