"""One matplotlib figure per chart kind and thread, made once and drawn again for the next report.

A report figure's fixed cost is its setup, not its data: a new ``Axes`` makes its
spines, axis and tick artists (~5 ms), and the first draw makes every tick (a
``Tick`` is three ``Line2D`` and two ``Text``, ~0.5 ms each); for the session
report's four charts that was about 90 ms of a ~200 ms session end (issue 25,
docs/benchmarks.md). :func:`reused_figure` keeps each kind's figure with its axes
and ticks, and before it is drawn again removes everything the chart added
(lines, collections, patches, texts, images, containers, legends), resets the
colour cycle and the data limits, and turns autoscaling back on: the chart then
draws into it as into a new figure, byte for byte the same SVG
(``tests/report/test_figure_pool.py``).

Per thread (``threading.local``): matplotlib figures are not safe to share between
threads. A chart sets everything it depends on at every call (labels, ticks it
fixes, aspect, size, margins); the rc parameters are those of the figure's first
use in the thread.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

__all__ = ["clear_pool", "reused_figure"]

_local = threading.local()


def reused_figure(kind: str, make: Callable[[], Any]) -> Any:
    """This thread's figure of chart ``kind``: made by ``make()`` the first time
    (the chart adds its axes to it then), afterwards the same figure with its axes
    emptied (:func:`_empty`). The caller draws into ``fig.axes``."""
    pool: dict[str, Any] = _local.__dict__.setdefault("figures", {})
    fig = pool.get(kind)
    if fig is None:
        fig = pool[kind] = make()
    else:
        _empty(fig)
    return fig


def clear_pool() -> None:
    """Forget this thread's figures (the next chart of each kind makes a new one)."""
    _local.__dict__.pop("figures", None)


def _empty(fig: Any) -> None:
    """Remove what a chart drew into ``fig``; keep the axes, their ticks and formatting."""
    for legend in list(fig.legends):
        legend.remove()
    for text in list(fig.texts):
        text.remove()
    for ax in fig.axes:
        for container in list(ax.containers):
            container.remove()
        for artist in [*ax.lines, *ax.collections, *ax.patches, *ax.texts, *ax.images, *ax.artists, *ax.tables]:
            artist.remove()
        if ax.legend_ is not None:
            ax.legend_.remove()
        ax.set_prop_cycle(None)  # the colour cycle starts over, as on new axes
        ax.relim()  # no artists left: the data limits are empty and ignored by the next ones
        ax.ignore_existing_data_limits = True
        ax.set_autoscale_on(True)
