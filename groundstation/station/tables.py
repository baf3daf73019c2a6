"""Append-only numeric tables for the live display (route, calibration cloud)."""
from __future__ import annotations

import numpy as np

__all__ = ["GrowingTable"]


class GrowingTable:
    """Append-only float table (amortised doubling) with a row cap."""

    def __init__(self, cols: int, cap: int) -> None:
        self.buf = np.empty((1024, cols))
        self.n = 0
        self.cap = cap

    def append(self, row) -> None:
        if self.n >= self.cap:
            return
        if self.n == len(self.buf):
            self.buf = np.concatenate([self.buf, np.empty_like(self.buf)])
        self.buf[self.n] = row
        self.n += 1

    def view(self) -> np.ndarray:
        return self.buf[: self.n]

    def clear(self) -> None:
        self.n = 0

    def drop_oldest(self, k: int) -> None:
        """Forget the first k rows (a bounded live history)."""
        k = min(max(int(k), 0), self.n)
        self.buf[: self.n - k] = self.buf[k: self.n]
        self.n -= k
