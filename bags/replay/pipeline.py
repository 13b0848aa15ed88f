"""Replay as a pipeline of four threads: :class:`Prefetch` reads the bag's next frames ahead
(read, synchronized, decoded), the caller maps the current one, an :class:`InOrder` scores the
frame mapped before it and another writes the frame scored before that (its messages in the
output bag, its picture).

Reading, decoding, scoring and writing spend much of their time in C code that releases the GIL
(MCAP chunk decompression, image conversion, numpy, OpenCV's distance transforms, PNG), so on a
machine with a free core the stages overlap. Order is kept at both ends: items and an exception
of the iterator arrive in order (the exception after the items before it), and the submitted
calls run one after another in submission order.
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
        self._thread = threading.Thread(target=self._run, name="read-ahead", daemon=True)
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


class InOrder:
    """Runs submitted calls one after another, in submission order, in a daemon thread; at
    most ``depth`` wait. The first exception a call raises is re-raised by the next
    :meth:`submit` or by :meth:`close` (the calls after it are skipped).
    """

    def __init__(self, depth: int = 2) -> None:
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._abandon = threading.Event()
        self._thread = threading.Thread(target=self._run, name="in-order", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            call = self._queue.get()
            if call is None:
                return
            if self._error is None and not self._abandon.is_set():
                fn, args = call
                try:
                    fn(*args)
                except BaseException as exc:  # noqa: BLE001 - handed to the submitter
                    self._error = exc

    def _raise(self) -> None:
        if self._error is not None:
            exc, self._error = self._error, None
            self._abandon.set()  # the calls after a failed one are skipped
            raise exc

    def submit(self, fn, *args) -> None:
        """Queue ``fn(*args)`` (waits while ``depth`` calls wait)."""
        self._raise()
        self._queue.put((fn, args))

    def close(self, abandon: bool = False) -> None:
        """Wait for the queued calls (``abandon``: skip those not started), then re-raise the
        first exception of a call, if any (not when abandoning: the caller has its own).
        """
        if abandon:
            self._abandon.set()
        self._queue.put(None)
        self._thread.join()
        if not abandon:
            self._raise()


__all__ = ["InOrder", "Prefetch"]
