"""The frame writer of an acquisition: frames captured by the engine are encoded, stored and
committed to the run store by three threads, through bounded queues, while the next frame is
captured (see :mod:`station.acquisition.acquire`).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

import numpy as np

from station.acquisition.run_store import FrameMeta, RunStore
from station.errors import StationError, describe_os_error

WRITER_QUEUE_FRAMES = 4  # frames captured ahead of the writer (memory: this many frames)


class AcquisitionError(StationError):
    """The run cannot start or cannot go on; the message says where and why."""


class FrameWriter:
    """Store writes behind the capture loop, in three threads that work on successive frames
    at once: encode (checks, shard bytes and crc32c: CPU), store (shard and metadata files
    handed to the kernel) and commit (barrier, then the done flag: waits for the disk).
    Frames pass every stage in order, so each keeps its durability order (shard, metadata,
    sync, done flag) and an interruption loses at most the frames in flight: the ``depth``
    queued, plus one per stage. Other writes (:meth:`submit`) run in the commit stage, in
    order with the frames. ``depth`` 0: every write in the caller's thread, serially.
    :meth:`submit` and :meth:`submit_frame` block while the queue is full and raise the
    writer's first error as :class:`AcquisitionError`; after an error nothing more is
    written or marked done. :meth:`close` writes what is queued and stops the threads."""

    BUFFERS = 2  # shard buffers: one being encoded while the other is being stored

    def __init__(self, store: RunStore, depth: int = WRITER_QUEUE_FRAMES) -> None:
        self.store = store
        self.error: BaseException | None = None
        self.failed_on = ""
        self.reported = False
        self._failed_seq: int | None = None
        self._seq = 0
        self._lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue(maxsize=max(int(depth), 1))
        self._threads: list[threading.Thread] = []
        if depth > 0:
            self._codecs: queue.Queue = queue.Queue()
            for _ in range(self.BUFFERS):
                self._codecs.put(store.new_codec())
            to_store: queue.Queue = queue.Queue(maxsize=1)
            to_commit: queue.Queue = queue.Queue(maxsize=1)
            for name, stage, src, dst in (("encode", self._encode, self._queue, to_store),
                                          ("store", self._store, to_store, to_commit),
                                          ("commit", self._commit, to_commit, None)):
                t = threading.Thread(target=self._loop, args=(stage, src, dst),
                                     name=f"run-store {name}", daemon=True)
                t.start()
                self._threads.append(t)

    def submit(self, what: str, fn: Callable[..., object], *args: object) -> None:
        """Run ``fn(*args)`` in the writer, after the frames submitted before it; ``what``
        names it in an error message."""
        self._put("call", what, (fn, args))

    def submit_frame(self, what: str, depth: int, pattern: int, image: np.ndarray,
                     meta: FrameMeta) -> None:
        """Write a frame (``RunStore.write_frame``) in the writer; ``image`` must not change
        until it is written."""
        self._put("frame", what, (depth, pattern, image, meta))

    def _put(self, kind: str, what: str, args: tuple) -> None:
        self._seq += 1
        item = (kind, what, args, self._seq)  # seq: frames before a failed one still finish
        if not self._threads:
            for stage in (self._encode, self._store, self._commit):
                item = self._run(stage, item)
            self.raise_error()
            return
        self.raise_error()
        while True:
            try:
                self._queue.put(item, timeout=0.05)
                return
            except queue.Full:
                self.raise_error()

    def _encode(self, item: tuple) -> tuple:
        kind, what, args, seq = item
        if kind != "frame":
            return item
        if not self._threads:
            return kind, what, (self.store.encode_frame(*args), None), seq
        codec = self._codecs.get()  # free again once the shard is stored
        try:
            return kind, what, (self.store.encode_frame(*args, codec=codec), codec), seq
        except BaseException:
            self._codecs.put(codec)
            raise

    def _store(self, item: tuple) -> tuple:
        kind, what, args, seq = item
        if kind != "frame":
            return item
        encoded, codec = args
        try:
            return kind, what, (self.store.store_encoded(encoded), None), seq
        finally:
            if codec is not None:
                self._codecs.put(codec)

    def _commit(self, item: tuple) -> None:
        kind, what, args, _ = item
        if kind == "frame":
            self.store.commit(args[0])
        else:
            fn, fargs = args
            fn(*fargs)

    def _run(self, stage: Callable[[tuple], object], item: tuple):
        """``stage(item)``, or nothing for an item submitted after one that failed (in any
        stage; the earliest failure is the error kept): items before it still finish."""
        if item is None:
            return None
        failed = self._failed_seq
        if failed is not None and item[3] > failed:
            self._release(item)
            return None
        try:
            return stage(item)
        except BaseException as exc:  # noqa: BLE001 - reported to the capture loop
            with self._lock:
                if self._failed_seq is None or item[3] < self._failed_seq:
                    self.error, self.failed_on, self._failed_seq = exc, item[1], item[3]
            return None

    def _release(self, item: tuple | None) -> None:
        """Give back the shard buffer of a frame dropped after an error."""
        if item is not None and item[0] == "frame" and len(item[2]) == 2 and \
                item[2][1] is not None and self._threads:
            self._codecs.put(item[2][1])

    def _loop(self, stage: Callable[[tuple], object], src: queue.Queue,
              dst: queue.Queue | None) -> None:
        while True:
            item = src.get()
            if item is None:
                if dst is not None:
                    dst.put(None)
                return
            out = self._run(stage, item)
            if dst is not None and out is not None:
                dst.put(out)

    def raise_error(self) -> None:
        """Raise the writer's error (once) as an :class:`AcquisitionError`."""
        if self.error is None or self.reported:
            return
        self.reported = True
        exc = self.error
        why = describe_os_error(exc) if isinstance(exc, OSError) else f"{exc}"
        raise AcquisitionError(
            f"{self.store.path}: could not write {self.failed_on}: {why}; the frames written "
            "before it are done and kept") from exc

    def close(self) -> None:
        """Write what is queued, stop the threads, then raise a writer error not yet raised."""
        if self._threads and self._threads[0].is_alive():
            self._queue.put(None)
        for t in self._threads:
            t.join()
        if self.error is None:
            try:
                self.store.flush()
            except BaseException as exc:  # noqa: BLE001 - reported below
                self.error, self.failed_on = exc, "the done flags"
        self.raise_error()
