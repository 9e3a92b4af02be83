"""Fixtures of the catalog tests: a real PostgreSQL server started by the tests
(pg_server.py: initdb and pg_ctl of the Debian ``postgresql`` package on a temporary
folder and a loopback port, as the ``postgres`` user when the tests run as root), and
``catalog_url``: each test once on SQLite and once on PostgreSQL (a fresh database each)."""

from __future__ import annotations

import pytest
from pg_server import new_database, running_server


@pytest.fixture(scope="session")
def postgres_server():
    """``postgresql://crossfield@127.0.0.1:PORT`` of a server running for the test session."""
    with running_server() as url:
        yield url


@pytest.fixture(params=["sqlite", "postgresql"])
def catalog_url(request, tmp_path):
    """A new, empty catalog: a SQLite file, or a new database on the test PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'catalog.sqlite'}"
    return new_database(request.getfixturevalue("postgres_server"))
