"""Read ahead: the items of an iterator produced on a second thread (replay's frame decode).

One job: :func:`ahead` runs a generator in a daemon thread that keeps up to
``depth`` items ready in a bounded queue, so that reading and decoding the
next stereo pair (file reads, chunk CRC and decompression, which release the
GIL) overlaps the processing of the current one. The items, their order and
any exception the generator raises (re-raised in the consumer, at the same
point of the sequence) are those of iterating the generator directly. When
the consumer stops early (``break``, an exception, the generator closed),
the producer is told to stop and its thread ends at its next item.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator
from typing import TypeVar

__all__ = ["ahead"]

T = TypeVar("T")

_DONE = object()
#: how often (s) a producer waiting on a full queue looks whether the consumer has gone
_POLL_S = 0.1


def ahead(produce: Callable[[], Iterator[T]], depth: int = 2, name: str = "read-ahead") -> Iterator[T]:
    """The items of ``produce()``, produced on a thread ``depth`` items ahead of the consumer."""
    if depth < 1:
        raise ValueError(f"depth must be >= 1, got {depth}")
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item: object) -> bool:
        while not stop.is_set():
            try:
                items.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        try:
            for item in produce():
                if not put((item, None)):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            put((_DONE, exc))
            return
        put((_DONE, None))

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    try:
        while True:
            item, error = items.get()
            if item is _DONE:
                thread.join()  # it has handed over its last item: it ends now
                if error is not None:
                    raise error
                return
            yield item
    finally:
        stop.set()  # a consumer that stops early: the producer ends at its next item
