"""The session catalog: every session's facts, characteristics, seal and station health in
one database (SQLite embedded, PostgreSQL for a plant), with queries, SPC trends and the
audit's outside anchor (docs/catalog.md).

From Python::

    import crossfield.catalog
    cat = crossfield.catalog.open("recordings/catalog.sqlite")
    cat.add("recordings/20261203-114730-table3")
    df = cat.characteristics(name="L03", since="2026-12-01")   # a pandas DataFrame
"""

from __future__ import annotations

from typing import Any

__all__ = ["Catalog", "open"]


def __getattr__(name: str) -> Any:
    # lazy: `crossfield --help` imports crossfield.catalog.commands, not SQLAlchemy and pandas
    if name in __all__:
        from crossfield.catalog import query

        return getattr(query, name)
    raise AttributeError(f"module 'crossfield.catalog' has no attribute {name!r}")
