"""A one-slot mailbox and the worker thread that drains it.

Subscription callbacks must stay cheap: they put the latest synchronized set into a
:class:`LatestSlot`; the :class:`Worker` takes it and does the heavy work (decode, map,
publish). A set that is replaced before the worker took it is dropped and counted, so work
never queues up without bound when mapping is slower than the cameras.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestSlot(Generic[T]):
    """Thread-safe single-item mailbox keeping only the newest item."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._closed = False
        self.dropped = 0

    def put(self, item: T) -> bool:
        """Store ``item``; returns True if it replaced an item not yet taken (that one is dropped)."""
        with self._cond:
            replaced = self._item is not None
            if replaced:
                self.dropped += 1
            self._item = item
            self._cond.notify()
        return replaced

    def take(self, timeout: float | None = None) -> T | None:
        """Wait for and remove the newest item; None on timeout or when closed."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        """Wake every waiter; further takes return None immediately."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._closed


class Worker:
    """Background thread calling ``handle(item)`` for each item taken from a slot.

    Exceptions from ``handle`` go to ``on_error`` and the loop goes on: one bad frame must not
    stop the node.
    """

    def __init__(
        self,
        slot: LatestSlot,
        handle: Callable[[object], None],
        on_error: Callable[[BaseException], None],
        name: str = "bev-worker",
    ) -> None:
        self._slot = slot
        self._handle = handle
        self._on_error = on_error
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Close the slot and join the thread."""
        self._slot.close()
        self._thread.join(timeout)

    def _run(self) -> None:
        while not self._slot.closed:
            item = self._slot.take(timeout=0.5)
            if item is None:
                continue
            try:
                self._handle(item)
            except Exception as exc:  # noqa: BLE001 - reported, never fatal
                self._on_error(exc)
