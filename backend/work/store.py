"""Scenes and BVHs kept by content hash, least recently used evicted, bounded by bytes.

One `Store` holds both kinds of entry so that a single byte budget (`--cache-mb`)
covers everything the service keeps. Keys are strings: a scene is its scene id, a
BVH is `"<scene id>/bvh/<method>/<leaf size>"`. Thread-safe: routes read it on the
event loop and the device worker inserts BVHs from its own thread.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

# Per-node size of an engine BVH when it does not expose its arrays: two float3
# bounds plus two int32 links, padded (an estimate only used for cache accounting).
_NODE_BYTES_ESTIMATE = 32


@dataclass
class Entry:
    value: Any
    nbytes: int


def bvh_key(scene_id: str, method: str, leaf_size: int) -> str:
    """The cache key of a BVH built with these parameters."""
    return f"{scene_id}/bvh/{method}/{leaf_size}"


def _array(value: Any) -> tuple[int, int] | None:
    """(address, bytes) of a numpy or Warp array; None for anything else."""
    interface = getattr(value, "__array_interface__", None)  # numpy
    if isinstance(interface, dict) and isinstance(getattr(value, "nbytes", None), int):
        return interface["data"][0], value.nbytes
    capacity = getattr(value, "capacity", None)  # wp.array
    if isinstance(capacity, int):
        return getattr(value, "ptr", None) or id(value), capacity
    return None


def _arrays(value: Any, depth: int = 1) -> list[tuple[int, int]]:
    """The arrays in `value`: itself, a tuple/list's items, a Warp struct's array fields,
    or, `depth` levels down, an object's attributes (a Bvh's DeviceMesh)."""
    found = _array(value)
    if found is not None:
        return [found]
    if isinstance(value, tuple | list):
        return [a for v in value for a in _arrays(v, 0)]
    struct = getattr(value, "_cls", None)  # a @wp.struct instance: its fields
    if struct is not None and isinstance(getattr(struct, "vars", None), dict):
        return [a for name in struct.vars for a in _arrays(getattr(value, name, None), 0)]
    if depth > 0 and hasattr(value, "__dict__"):
        return [a for v in vars(value).values() for a in _arrays(v, depth - 1)]
    return []


def bvh_nbytes(bvh: Any) -> int:
    """Bytes a built BVH holds: host arrays, device arrays and its struct's arrays, each
    buffer once (on CPU the device mesh is the host arrays themselves)."""
    total = sum(dict(_arrays(bvh)).values())
    if total == 0:  # an engine object we cannot inspect: estimate from its statistics
        total = int(getattr(getattr(bvh, "stats", None), "nodes", 0)) * _NODE_BYTES_ESTIMATE
    return max(total, 1)


class Store:
    """A byte-bounded LRU map; the newest entry and its scene are kept even over budget."""

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.max_bytes = max_bytes
        self._entries: OrderedDict[str, Entry] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.evictions = 0

    def get(self, key: str) -> Any | None:
        """The value for `key` (now most recently used), or None."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return entry.value

    def __contains__(self, key: str) -> bool:
        # A membership test is not a use: it does not refresh the entry's age.
        with self._lock:
            return key in self._entries

    def put(self, key: str, value: Any, nbytes: int) -> list[str]:
        """Insert or replace `key`; return the keys evicted to stay within budget."""
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._entries[key] = Entry(value, nbytes)
            self._bytes += nbytes
            # The newest entry and the scene it belongs to are never the victims.
            protected = {key, key.split("/bvh/")[0]}
            evicted = []
            for victim in list(self._entries):
                if self._bytes <= self.max_bytes:
                    break
                if victim not in protected and victim in self._entries:
                    evicted.extend(self._drop_with_dependents(victim))
            self.evictions += len(evicted)
            return evicted

    def _drop_with_dependents(self, key: str) -> list[str]:
        """Remove `key` and its BVHs (a BVH is useless without its scene); lock held."""
        dropped = [k for k in self._entries if k == key or k.startswith(key + "/")]
        for k in dropped:
            self._bytes -= self._entries.pop(k).nbytes
        return dropped

    def discard(self, prefix: str) -> list[str]:
        """Remove every entry whose key starts with `prefix`; return their keys."""
        with self._lock:
            dropped = [k for k in self._entries if k.startswith(prefix)]
            for k in dropped:
                self._bytes -= self._entries.pop(k).nbytes
            return dropped

    def values_of(self, kind: type) -> list[Any]:
        """The values that are instances of `kind` (a snapshot; none is touched)."""
        with self._lock:
            return [e.value for e in self._entries.values() if isinstance(e.value, kind)]

    def latest_with_prefix(self, prefix: str) -> tuple[str, Any] | None:
        """The most recently used entry whose key starts with `prefix` (not touched)."""
        with self._lock:
            for key in reversed(self._entries):
                if key.startswith(prefix):
                    return key, self._entries[key].value
            return None

    def usage(self) -> dict[str, int]:
        """Bytes used, the budget, and entry counts by kind."""
        with self._lock:
            bvhs = sum(1 for k in self._entries if "/bvh/" in k)
            return {
                "bytes": self._bytes,
                "max_bytes": self.max_bytes,
                "scenes": len(self._entries) - bvhs,
                "bvhs": bvhs,
                "evictions": self.evictions,
            }
