"""Shared memory between the serve processes: numpy views on ``multiprocessing.shared_memory``.

``SharedArrays`` is one named block holding several float64 arrays (a layout {name: shape}).
``VersionedBuffer`` is a single-writer, many-reader seqlock over a double buffer: the writer
fills the slot readers are *not* pointed at, bumping that slot's sequence number to odd before
and to even after, then flips ``latest``; a reader copies the latest slot and retries if its
sequence number was odd or changed meanwhile. Never blocks the writer; no pickling, no locks.
(Relies on in-order stores as on x86-64 / TSO; numpy element stores are not reordered across
calls by the interpreter.)
"""

from __future__ import annotations

import secrets
from multiprocessing import shared_memory

import numpy as np


class SharedArrays:
    """Several float64 arrays in one shared-memory block, created by the parent, attached by children."""

    def __init__(self, layout: dict[str, tuple[int, ...]], name: str | None = None, create: bool = False) -> None:
        self.layout = {k: tuple(int(s) for s in v) for k, v in layout.items()}
        sizes = {k: int(np.prod(v)) for k, v in self.layout.items()}
        nbytes = 8 * max(1, sum(sizes.values()))
        if create:
            name = name or f"tgnn_{secrets.token_hex(6)}"
            self.shm = shared_memory.SharedMemory(name=name, create=True, size=nbytes)
            self.shm.buf[:nbytes] = bytes(nbytes)
        else:
            self.shm = _attach(name)
        self.name = self.shm.name
        self.owner = create
        self.arrays: dict[str, np.ndarray] = {}
        offset = 0
        for k, shape in self.layout.items():
            n = sizes[k]
            self.arrays[k] = np.ndarray(shape, dtype=np.float64, buffer=self.shm.buf, offset=8 * offset)
            offset += n

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def spec(self) -> dict:
        """Picklable description to attach from another process."""
        return {"name": self.name, "layout": self.layout}

    @classmethod
    def attach(cls, spec: dict) -> "SharedArrays":
        return cls(spec["layout"], name=spec["name"], create=False)

    def close(self) -> None:
        self.arrays.clear()
        try:
            self.shm.close()
        except BufferError:  # a view still alive somewhere; the OS frees it at exit
            pass
        if self.owner:
            try:
                self.shm.unlink()
            except FileNotFoundError:
                pass


def _attach(name: str) -> shared_memory.SharedMemory:
    """Attach to an existing block. Spawned children share the parent's resource tracker, so the
    (deduplicated) registration is released when the creator unlinks."""
    return shared_memory.SharedMemory(name=name, create=False)


def versioned_layout(payload: int) -> tuple[int, ...]:
    """Shape of a VersionedBuffer's backing array: header (latest, count) + 2 slots of (seq, payload)."""
    return (2 + 2 * (1 + payload),)


class VersionedBuffer:
    """Seqlock double buffer over a float64 array of shape ``versioned_layout(payload)``."""

    def __init__(self, array: np.ndarray, payload: int) -> None:
        self.payload = payload
        self.header = array[:2]                               # [latest slot, publish count]
        self.slots = array[2:].reshape(2, 1 + payload)        # [slot, (seq, payload...)]
        self.seq = [self.slots[0, :1], self.slots[1, :1]]     # views, for cheap scalar access
        self.data = [self.slots[0, 1:], self.slots[1, 1:]]

    # writer --------------------------------------------------------------------------------
    def publish(self, values: np.ndarray) -> int:
        """Copy ``values`` [payload] into the idle slot and make it the latest; returns the version."""
        s = 1 - int(self.header[0])
        self.seq[s][0] += 1.0          # odd: writing
        self.data[s][:] = values
        self.seq[s][0] += 1.0          # even: consistent
        self.header[0] = s
        self.header[1] += 1.0
        return int(self.header[1])

    # reader --------------------------------------------------------------------------------
    def version(self) -> int:
        return int(self.header[1])

    def read(self, out: np.ndarray, tries: int = 64) -> bool:
        """Copy the latest consistent payload into ``out``; False if none yet or torn ``tries`` times.

        Writers that need versions put a counter in the payload (it is read consistently with it).
        """
        if self.header[1] == 0.0:
            return False
        for _ in range(tries):
            s = int(self.header[0])
            seq0 = self.seq[s][0]
            if seq0 % 2.0 == 1.0:
                continue
            np.copyto(out, self.data[s])
            if self.seq[s][0] == seq0:
                return True
        return False
