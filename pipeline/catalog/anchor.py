"""The audit's outside anchor: a recording's chain head, SHA-256 and signature against the
catalog's row of its session (``crossfield audit SESSION --catalog URL``, ``crossfield
catalog verify``).

The chain head is compared by the audit's own seal check (``expect_head``, the same
comparison as ``crossfield audit --expect-head``: :func:`crossfield.audit.report.seal_check`);
this module adds what the catalog also kept: the file's SHA-256 and the seal's signature
(and key). A session rewritten consistently after it was catalogued (raw bytes changed,
everything re-derived and the chain recomputed) passes a plain audit, which proves only
self-consistency, and fails here: its head and SHA-256 are not the ones recorded when it
was made. What this proves is "agreement with the catalog's row": as strong as the
catalog is out of the forger's reach (docs/catalog.md, "The audit's anchor").
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from crossfield.errors import ConfigError

#: The level a passed anchor check adds to the seal's ``levels``.
LEVEL = "agreement with the catalog"


def row_problems(seal_result: Mapping[str, Any], row: Mapping[str, Any], url: str) -> list[str]:
    """What in the audit's seal result (``AuditReport.seal``, checked with ``expect_head`` =
    the row's chain head) differs from the catalog's row beyond the head: the file SHA-256,
    the seal's signature and its key."""
    problems = []
    if seal_result.get("file_sha256") != row["file_sha256"]:
        problems.append(
            f"the file's SHA-256 {seal_result.get('file_sha256')} is not the catalog's {row['file_sha256']} "
            f"(session {row['session_id']} in {url})"
        )
    sidecar = seal_result.get("sidecar") or {}
    kept = row.get("signature")
    if kept is None and row.get("signature_json"):
        kept = json.loads(row["signature_json"])
    if kept is not None and sidecar.get("signature") != kept:
        problems.append(
            f"the seal's signature is not the one catalogued for session {row['session_id']} "
            f"(catalogued key {kept.get('public_key')}, the seal's "
            f"{(sidecar.get('signature') or {}).get('public_key', 'none: unsigned')})"
        )
    return problems


def anchored(report: Any, row: Mapping[str, Any] | None, url: str, session_id: str) -> Any:
    """``report`` (an AuditReport whose seal was checked with the row's head) with the
    catalog's verdict folded into its seal section: problems added, ``catalog`` set, the
    level raised to :data:`LEVEL` when everything agrees."""
    sealed = report.seal
    if row is None:
        sealed.setdefault("problems", []).append(f"session {session_id} is not in the catalog {url}")
        sealed["passed"] = False
        sealed["catalog"] = {"url": url, "session_id": session_id, "found": False}
        return report
    problems = row_problems(sealed, row, url)
    sealed.setdefault("problems", []).extend(problems)
    sealed["passed"] = bool(sealed.get("passed")) and not problems
    sealed["catalog"] = {
        "url": url,
        "session_id": session_id,
        "found": True,
        "chain_head": row["chain_head"],
        "file_sha256": row["file_sha256"],
        "public_key_fingerprint": row.get("public_key_fingerprint"),
    }
    if sealed["passed"]:
        sealed["levels"] = [*sealed.get("levels", []), LEVEL]
        sealed["level"] = LEVEL
    return report


def recording_session_id(path: str | Path) -> str:
    """The session id a recording states (its ``crossfield.session`` metadata)."""
    from crossfield.recording.facts import load_session_facts

    return load_session_facts(path).session_id


def audit_with_catalog(
    path: str | Path,
    pm: Any,
    catalog: str | Path | Any,
    *,
    reproduce: bool = True,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> Any:
    """``crossfield audit SESSION --catalog URL``: the audit with ``expect_head`` taken from
    the catalog's row of the recording's session, then the SHA-256 and signature compared
    with it (:func:`anchored`). ``catalog``: a URL or an open :class:`Catalog`. An
    ``expect_head`` given as well must agree with the catalog's (ConfigError otherwise)."""
    from crossfield.audit import audit
    from crossfield.audit.report import parse_head
    from crossfield.catalog.query import Catalog
    from crossfield.catalog.query import open as open_catalog

    path = Path(path)
    if path.is_dir():
        path = path / "session.mcap"
    cat = catalog if isinstance(catalog, Catalog) else open_catalog(catalog, migrate=False)
    try:
        session_id = recording_session_id(path)
        row = cat.seal(session_id)
        url = cat.url
    finally:
        if cat is not catalog:
            cat.close()
    head = row["chain_head"] if row is not None else expect_head
    if row is not None and expect_head is not None and parse_head(expect_head) != row["chain_head"]:
        raise ConfigError(
            f"--expect-head {expect_head} is not the chain head the catalog {url} keeps for "
            f"session {session_id} ({row['chain_head']})"
        )
    report = audit(path, pm, reproduce=reproduce, expect_head=head, public_key=public_key)
    return anchored(report, row, url, session_id)


def check_row(row: Mapping[str, Any], url: str) -> dict[str, Any]:
    """``crossfield catalog verify`` for one catalogued session: its recording's chain
    recomputed (:func:`crossfield.audit.chain.verify`), the seal checked with the
    catalog's head (the audit's :func:`seal_check`), the SHA-256 and signature compared
    with the row. No replay (``crossfield audit --catalog`` does that for one session).
    Plain data, so a Dask worker can return it."""
    from crossfield.audit.chain import verify
    from crossfield.audit.report import seal_check
    from crossfield.recording.integrity import file_sha256

    path = Path(row["folder"]) / str(row["recording"])
    out: dict[str, Any] = {"session_id": row["session_id"], "path": str(path)}
    if not path.is_file():
        return {**out, "passed": False, "problems": [f"{path}: the catalogued recording is gone"]}
    integrity = verify(path)
    seal_result = seal_check(path, integrity, file_sha256(path), expect_head=row["chain_head"])
    problems = [str(p) for p in integrity.problems]
    problems += list(seal_result["problems"]) + row_problems(seal_result, row, url)
    return {**out, "passed": integrity.passed and not problems, "problems": problems}


def verify_all(
    catalog: Any, *, scheduler: str | None = None, workers: int | None = None, memory_limit: Any = "auto",
    progress: bool = False,
) -> list[dict[str, Any]]:
    """:func:`check_row` for every catalogued session: in this process, or on Dask
    (``crossfield.batch.engine``) when ``scheduler`` or ``workers`` is given."""
    rows = catalog.seals()
    url = catalog.url
    if scheduler is None and workers is None:
        return [check_row(r, url) for r in rows]
    from crossfield.batch import engine

    results: list[dict[str, Any] | None] = [None] * len(rows)

    def done(i: int, result: Any, error: str | None) -> None:
        results[i] = result if error is None else {
            "session_id": rows[i]["session_id"], "passed": False, "problems": [error],
            "path": str(Path(rows[i]["folder"]) / str(rows[i]["recording"])),
        }

    with engine.client(scheduler, workers, memory_limit=memory_limit) as c:
        engine.run_each(c, check_row, [(r, url) for r in rows], done, prefix="catalog-verify", progress=progress)
    return [r for r in results if r is not None]
