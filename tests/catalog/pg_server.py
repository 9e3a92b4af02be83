"""A throw-away PostgreSQL server (the Debian ``postgresql`` package's initdb and pg_ctl on
a temporary folder and a loopback port), for the catalog's tests (conftest.py) and
benchmark (bench/bench_catalog.py).

initdb refuses to run as root, and CI runs as root: the server's folder is then given to
the ``postgres`` system user the package creates and the tools run as that user
(``runuser -u postgres --``). Stopped with ``pg_ctl stop -m immediate``, folder removed.
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path


def pg_bin() -> Path:
    """The newest installed PostgreSQL's bin folder (AssertionError naming the package)."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    assert found, "the Debian package 'postgresql' is needed (make apt-packages)"
    return Path(found[-1]).parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running_server() -> Iterator[str]:
    """``postgresql://crossfield@127.0.0.1:PORT`` of a server running inside the ``with``."""
    binary = pg_bin()
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

    try:
        run(str(binary / "initdb"), "-D", str(data), "-U", "crossfield", "-A", "trust", "-E", "UTF8", "--no-sync")
        options = f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off -c full_page_writes=off"
        run(str(binary / "pg_ctl"), "-D", str(data), "-o", options, "-l", str(root / "log"), "-w", "-t", "60",
            "start")
        yield f"postgresql://crossfield@127.0.0.1:{port}"
    finally:
        if data.exists():
            subprocess.run([*as_user, str(binary / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
                           capture_output=True, env=env, timeout=60)
        shutil.rmtree(root, ignore_errors=True)


def new_database(server: str) -> str:
    """The URL of a new, empty database on ``server``."""
    import psycopg

    name = f"t_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(f"{server}/postgres", autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    return f"{server}/{name}"
