"""Fixtures of the catalog tests: a real PostgreSQL server started by the tests (the Debian
``postgresql`` package's initdb and pg_ctl on a temporary folder and a loopback port), and
``catalog_url``, each test once on SQLite and once on PostgreSQL (a fresh database each).

initdb refuses to run as root, and CI runs as root: the server's folder is then given to
the ``postgres`` system user the package creates and the tools run as that user
(``runuser -u postgres --``). The server is stopped (``pg_ctl stop -m immediate``) and its
folder removed at the end of the session.
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path

import pytest


def _pg_bin() -> Path:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    assert found, "the Debian package 'postgresql' is needed (make apt-packages)"
    return Path(found[-1]).parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def postgres_server():
    """``postgresql://crossfield@127.0.0.1:PORT/`` of a server running for the test session."""
    binary = _pg_bin()
    root = Path(tempfile.mkdtemp(prefix="crossfield-pg-"))
    data = root / "data"
    as_user: list[str] = []
    if os.geteuid() == 0:
        import pwd

        pw = pwd.getpwnam("postgres")
        os.chown(root, pw.pw_uid, pw.pw_gid)
        os.chmod(root, 0o700)
        as_user = ["runuser", "-u", "postgres", "--"]
    port = _free_port()
    env = {**os.environ, "LC_ALL": "C.UTF-8"}

    def run(*cmd: str) -> None:
        result = subprocess.run([*as_user, *cmd], capture_output=True, text=True, env=env, timeout=120)
        assert result.returncode == 0, f"{cmd[0]}: {result.stdout[-1500:]}{result.stderr[-1500:]}"

    run(str(binary / "initdb"), "-D", str(data), "-U", "crossfield", "-A", "trust", "-E", "UTF8", "--no-sync")
    options = f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off -c full_page_writes=off"
    run(str(binary / "pg_ctl"), "-D", str(data), "-o", options, "-l", str(root / "log"), "-w", "-t", "60", "start")
    try:
        yield f"postgresql://crossfield@127.0.0.1:{port}"
    finally:
        subprocess.run([*as_user, str(binary / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
                       capture_output=True, env=env, timeout=60)
        shutil.rmtree(root, ignore_errors=True)


def _new_database(server: str) -> str:
    import psycopg

    name = f"t_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(f"{server}/postgres", autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    return f"{server}/{name}"


@pytest.fixture(params=["sqlite", "postgresql"])
def catalog_url(request, tmp_path):
    """A new, empty catalog: a SQLite file, or a new database on the test PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'catalog.sqlite'}"
    return _new_database(request.getfixturevalue("postgres_server"))
