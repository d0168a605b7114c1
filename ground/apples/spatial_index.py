"""Apples by grid cell, for the merges' search: the apples near a point in time independent of the map's size."""

from __future__ import annotations

import numpy as np

from ground.apples.association import Apple


class SpatialIndex:
    """Apples by grid cell (``cell_m`` = the merge search radius): the apples near a point, from the 27 cells around
    it, in time independent of the map's size."""

    def __init__(self, cell_m: float):
        self.cell = float(cell_m)
        self._cells: dict[tuple[int, int, int], dict[int, Apple]] = {}
        self._where: dict[int, tuple[int, int, int]] = {}

    def _key(self, X) -> tuple[int, int, int]:
        return tuple(int(v) for v in np.floor(np.asarray(X, float)[:3] / self.cell))

    def __len__(self) -> int:
        return len(self._where)

    def put(self, a: Apple) -> None:
        """Add an apple, or move it to the cell of its (updated) position."""
        new = self._key(a.X)
        old = self._where.get(a.id)
        if old == new:
            return
        if old is not None:
            self._cells[old].pop(a.id, None)
            if not self._cells[old]:
                del self._cells[old]
        self._cells.setdefault(new, {})[a.id] = a
        self._where[a.id] = new

    def remove(self, a: Apple) -> None:
        key = self._where.pop(a.id, None)
        if key is not None:
            self._cells[key].pop(a.id, None)
            if not self._cells[key]:
                del self._cells[key]

    def near(self, X, r: float) -> list[Apple]:
        kx, ky, kz = self._key(X)
        X = np.asarray(X, float)
        out = []
        n = max(1, int(np.ceil(r / self.cell)))  # a radius beyond one cell (the map's units changed): more cells
        span = range(-n, n + 1)
        for dx in span:
            for dy in span:
                for dz in span:
                    for a in self._cells.get((kx + dx, ky + dy, kz + dz), {}).values():
                        if np.linalg.norm(a.X - X) <= r:
                            out.append(a)
        return out
