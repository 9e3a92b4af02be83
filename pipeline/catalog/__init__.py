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

from crossfield.catalog.query import Catalog, open

__all__ = ["Catalog", "open"]
