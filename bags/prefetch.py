"""Read ahead: the next items of an iterator produced by a background thread while the caller
works on the current one (replay: the bag's next frames are read, synchronized and decoded while
the current frame is mapped, scored and written).

Reading and decoding spend much of their time in C code that releases the GIL (MCAP chunk
decompression, image conversion, numpy), so on a machine with a free core the two overlap.
Items and exceptions arrive in order: an exception the iterator raises is re-raised by the
consumer at the point where the iterator raised it, after the items before it.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from typing import Generic, TypeVar

T = TypeVar("T")

_END = object()


class Prefetch(Generic[T]):
    """Iterate over ``source`` with up to ``depth`` items read ahead by a daemon thread.

    :meth:`close` (also on leaving a ``with`` block) stops the thread and closes ``source``
    (a generator's ``finally`` blocks run) without reading it to the end.
    """

    def __init__(self, source: Iterator[T], depth: int = 4) -> None:
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        self._source = source
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="prefetch", daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        """Queue ``item`` unless stopped; False when stopped."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        try:
            for item in self._source:
                if not self._put((item, None)):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, in order
            self._put((_END, exc))
            return
        self._put((_END, None))

    def __iter__(self) -> Iterator[T]:
        while True:
            item, exc = self._queue.get()
            if item is _END:
                if exc is not None:
                    raise exc
                return
            yield item

    def close(self) -> None:
        """Stop reading ahead and close the source (its ``finally`` blocks run here)."""
        self._stop.set()
        self._thread.join()
        close = getattr(self._source, "close", None)
        if close is not None:
            close()

    def __enter__(self) -> Prefetch[T]:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["Prefetch"]
