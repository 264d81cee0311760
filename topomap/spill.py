"""Keyframe payloads held on disk while a map is built, so the build's memory does not grow with them.

A build keeps every keyframe's local features (for loop verification, the motion stage and the
calibration) and its encoded image (for the map file) until the map is saved. Held in memory they
are most of what a large build's memory grows by per node; :class:`Spill` writes them once to an
anonymous temporary file and hands back stand-ins — :class:`SpilledFeatures` (a :class:`Features`)
and :class:`SpilledBytes` — that read them back on demand through a small LRU working set (RTAB-Map's
working memory over its database is the model). Pickled (to a worker process or a Dask worker) a
stand-in travels as the plain value, so the receiving side never needs the file.

The file lives as long as the last stand-in that refers to it (the map built with it) and is
deleted by the operating system when it is closed, whatever happens to the process.
"""

from __future__ import annotations

import itertools
import os
import tempfile
import threading
from collections import OrderedDict

import numpy as np

from topomap.errors import TopomapError
from topomap.features import Features

__all__ = ["Spill", "SpilledFeatures", "SpilledBytes", "as_bytes"]


class Spill:
    """An append-only temporary file of arrays and byte strings with an LRU of ``working_set`` items
    read back. ``directory``: where the file is made (default: the system's temporary directory,
    ``TMPDIR``); a full disk raises :class:`TopomapError`."""

    def __init__(self, working_set: int = 64, directory: str | None = None):
        if working_set < 1:
            raise ValueError("a spill's working set holds at least one item")
        self.directory = directory or tempfile.gettempdir()
        self._file = tempfile.TemporaryFile(dir=self.directory)  # unlinked at once: no file is ever left behind
        self._fd = self._file.fileno()
        self._end = 0
        self._lock = threading.Lock()  # put/read may come from an executor's threads
        self._lru: OrderedDict[int, object] = OrderedDict()
        self._keys = itertools.count()  # not the offset (an empty item shares it with the next) nor id() (reused)
        self.working_set = working_set

    @property
    def bytes_written(self) -> int:
        return self._end

    def _write(self, data: bytes | memoryview) -> int:
        with self._lock:
            at = self._end
            try:
                written = os.pwrite(self._fd, data, at)
            except OSError as e:  # a full disk: say where, and what to do
                raise TopomapError(f"cannot hold the build's keyframes on disk in {self.directory}: "
                                   f"{e.strerror or e}; free space there or set TMPDIR to a larger disk") from None
            if written != len(data):
                raise TopomapError(f"cannot hold the build's keyframes on disk in {self.directory}: the disk is full; "
                                   "free space there or set TMPDIR to a larger disk")
            self._end += len(data)
            return at

    def _read(self, at: int, length: int) -> bytes:
        data = os.pread(self._fd, length, at)
        if len(data) != length:  # pragma: no cover - the file is private to this process
            raise OSError(f"the build's spill file is short at {at} ({len(data)} of {length} bytes)")
        return data

    def _cached(self, key: int, load):
        with self._lock:
            hit = self._lru.get(key)
            if hit is not None:
                self._lru.move_to_end(key)
                return hit
        value = load()
        with self._lock:
            self._lru[key] = value
            while len(self._lru) > self.working_set:
                self._lru.popitem(last=False)
        return value

    def put_features(self, f: Features) -> SpilledFeatures:
        kp = np.ascontiguousarray(f.keypoints)
        de = np.ascontiguousarray(f.descriptors)
        at = self._write(kp.tobytes() + de.tobytes())
        return SpilledFeatures(self, at, len(kp), (kp.dtype.str, kp.shape[1]), (de.dtype.str, de.shape[1]),
                               f.kind, tuple(f.image_size))

    def put_bytes(self, data: bytes) -> SpilledBytes:
        return SpilledBytes(self, self._write(data), len(data))

    def close(self) -> None:
        self._file.close()


class SpilledFeatures(Features):
    """:class:`Features` whose arrays live in a :class:`Spill`; read-only arrays, read on first use
    and kept while in the spill's working set. Its length needs no read."""

    def __init__(self, spill: Spill, at: int, n: int, kp: tuple[str, int], de: tuple[str, int], kind: str,
                 image_size: tuple[int, int]):
        # no dataclass __init__: the arrays are properties (frozen: set through object.__setattr__)
        for name, value in (("_spill", spill), ("_key", next(spill._keys)), ("_at", at), ("_n", n), ("_kp", kp), ("_de", de),
                            ("kind", kind), ("image_size", image_size)):
            object.__setattr__(self, name, value)

    def _arrays(self) -> tuple[np.ndarray, np.ndarray]:
        def load():
            (kt, kw), (dt, dw) = self._kp, self._de
            kp_bytes = self._n * kw * np.dtype(kt).itemsize
            raw = self._spill._read(self._at, kp_bytes + self._n * dw * np.dtype(dt).itemsize)
            kp = np.frombuffer(raw, kt, self._n * kw).reshape(self._n, kw)
            de = np.frombuffer(raw, dt, self._n * dw, offset=kp_bytes).reshape(self._n, dw)
            return kp, de

        return self._spill._cached(self._key, load)

    @property
    def keypoints(self) -> np.ndarray:  # type: ignore[override]
        return self._arrays()[0]

    @property
    def descriptors(self) -> np.ndarray:  # type: ignore[override]
        return self._arrays()[1]

    def __len__(self) -> int:
        return self._n

    def __repr__(self) -> str:
        return f"SpilledFeatures({self._n} {self.kind} features at {self.image_size})"

    def __eq__(self, other) -> bool:
        return self is other

    __hash__ = object.__hash__

    def __reduce__(self):
        kp, de = self._arrays()
        return Features, (kp.copy(), de.copy(), self.kind, self.image_size)


class SpilledBytes:
    """A byte string (an encoded keyframe image) that lives in a :class:`Spill`; ``bytes(x)`` reads
    it. Not cached: it is read once, when the map is written."""

    __slots__ = ("_spill", "_at", "_n")

    def __init__(self, spill: Spill, at: int, n: int):
        self._spill, self._at, self._n = spill, at, n

    def __bytes__(self) -> bytes:
        return self._spill._read(self._at, self._n)

    def __len__(self) -> int:
        return self._n

    def __reduce__(self):
        return bytes, (bytes(self),)


def as_bytes(data: bytes | SpilledBytes | None) -> bytes | None:
    """The bytes of a node's ``image_data``, spilled or not."""
    return None if data is None else bytes(data)
