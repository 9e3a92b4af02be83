"""Alembic's environment for the catalog: run programmatically by
:func:`crossfield.catalog.db.upgrade` (no alembic.ini), on the connection it hands over
in ``config.attributes["connection"]``."""

from __future__ import annotations

from alembic import context

from crossfield.catalog.schema import metadata

connection = context.config.attributes["connection"]
context.configure(
    connection=connection,
    target_metadata=metadata,
    render_as_batch=connection.dialect.name == "sqlite",  # SQLite alters a table by copying it
)
with context.begin_transaction():
    context.run_migrations()
