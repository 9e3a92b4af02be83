"""crossfield.recording.prefetch.ahead: the same items, order and errors as the generator itself."""

from __future__ import annotations

import threading
import time

import pytest

from crossfield.recording.prefetch import ahead


def test_same_items_in_the_same_order_produced_on_another_thread():
    threads = []

    def produce():
        for k in range(50):
            threads.append(threading.get_ident())
            yield k

    assert list(ahead(produce, depth=3)) == list(range(50))
    assert set(threads) == {threads[0]} and threads[0] != threading.get_ident()


def test_an_error_is_raised_in_the_consumer_after_the_items_before_it():
    def produce():
        yield 1
        yield 2
        raise ValueError("damaged at item 3")

    got = []
    with pytest.raises(ValueError, match="damaged at item 3"):
        for item in ahead(produce):
            got.append(item)
    assert got == [1, 2]


def test_a_consumer_that_stops_early_stops_the_producer():
    produced = []

    def produce():
        for k in range(10_000):
            produced.append(k)
            yield k

    for item in ahead(produce, depth=2):
        if item == 5:
            break
    time.sleep(0.5)
    assert len(produced) <= 5 + 2 + 2  # the consumer's items, the queue, one in hand
    with pytest.raises(ValueError):
        list(ahead(produce, depth=0))
