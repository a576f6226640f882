"""Host-side results kept for the inputs they were computed from, keyed by the arrays' bytes.

An edit session (the viewer, a sweep of edits) recomputes host tables that depend only on the
unedited cloud: its neighbour table, its spacing statistics. :class:`LastResults` keeps the last few
such results; a call with equal arrays (same dtype, shape and bytes) returns the kept result instead
of computing it again. Keys are BLAKE2b digests, so a hit costs one pass over the bytes.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable

import numpy as np


def array_key(*parts) -> tuple:
    """A hashable key of ``parts``: arrays by dtype, shape and the digest of their bytes; other
    (hashable) values as they are."""
    key = []
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            key.append((a.dtype.str, a.shape, hashlib.blake2b(a.view(np.uint8).reshape(-1), digest_size=16).digest()))
        else:
            key.append(p)
    return tuple(key)


class LastResults:
    """The results of the last ``size`` distinct keys (thread-safe; results are returned as kept, so
    they must not be modified: arrays are made read-only)."""

    def __init__(self, size: int = 2):
        self.size = int(size)
        self._kept: OrderedDict[Hashable, object] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, compute: Callable[[], object]):
        with self._lock:
            if key in self._kept:
                self._kept.move_to_end(key)
                return self._kept[key]
        value = compute()
        for leaf in value if isinstance(value, tuple) else (value,):
            if isinstance(leaf, np.ndarray):
                leaf.flags.writeable = False
        with self._lock:
            self._kept[key] = value
            while len(self._kept) > self.size:
                self._kept.popitem(last=False)
        return value


__all__ = ["LastResults", "array_key"]
