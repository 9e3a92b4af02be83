"""The audit's outside anchor: a session rewritten consistently after it was catalogued
(raw CMM bytes changed, every derived message re-derived, the chain recomputed by
crossfield's own writer) passes a plain audit and fails ``audit --catalog`` and
``crossfield catalog verify``."""

from __future__ import annotations

import argparse
import re
import shutil

import pytest
from session_tools import forge, record_session, shift_cfp_x  # tests/, on sys.path by tests/conftest.py

import crossfield.catalog
from crossfield.audit import audit
from crossfield.catalog.anchor import LEVEL, audit_with_catalog
from crossfield.catalog.commands import audit_command, main as catalog_main
from crossfield.chain.registry import make_plugin_manager
from crossfield.recording.reader import open_recording


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A real 2-frame session folder and, made once, its consistent forgery (session.mcap + seal)."""
    out = tmp_path_factory.mktemp("anchor")
    record_session(out, "orig", frames=2)
    folder = out / "orig"
    (folder / "report.json").exists() or pytest.fail("no report.json")
    with open_recording(folder / "session.mcap") as rec:
        raw = b"".join(m.data for m in rec.messages("/cmm/raw", decode=False, file_order=True))
    last_press = max(int(x) for x in re.findall(rb"\$CFP,([0-9]+),", raw))
    work = out / "forgery"
    work.mkdir()
    forge(folder / "session.mcap", work / "session.mcap", lambda b: shift_cfp_x(b, last_press, 0.038), work)
    return folder, work


def test_a_consistently_rechained_session_passes_a_plain_audit_and_fails_against_the_catalog(
    recorded, catalog_url, tmp_path, capsys
):
    original, work = recorded
    folder = tmp_path / "orig"
    shutil.copytree(original, folder)
    mcap = folder / "session.mcap"
    pm = make_plugin_manager()
    with crossfield.catalog.open(catalog_url) as cat:
        assert [r.status for r in cat.add(folder)] == ["added"]
    before = audit_with_catalog(mcap, pm, catalog_url, reproduce=False)
    assert before.seal["passed"] and before.seal["level"] == LEVEL, before.seal["problems"]
    catalogued_head = before.seal["catalog"]["chain_head"]
    # the rewrite after ingest: the forged file and its (self-consistent) seal replace the originals
    shutil.copy(work / "session.mcap", mcap)
    shutil.copy(work / "session.mcap.seal.json", folder / "session.mcap.seal.json")
    if catalog_url.startswith("sqlite"):  # the full audit with replay once: it passes
        plain = audit(mcap, pm)
        assert plain.passed, (plain.seal["problems"], plain.reproduction.get("differences"))
    plain = audit(mcap, pm, reproduce=False)
    assert plain.integrity.passed and plain.seal["passed"] and plain.seal["level"] == "self-consistency"
    assert plain.integrity.chain_sha256 != catalogued_head
    args = argparse.Namespace(recording=str(mcap), catalog=catalog_url, no_replay=True, expect_head=None,
                              public_key=None)
    anchored = audit_command(args, pm)  # what `crossfield audit S.mcap --catalog URL --no-replay` runs
    assert not anchored.passed and not anchored.seal["passed"]
    problems = " ".join(anchored.seal["problems"])
    assert f"is not the expected {catalogued_head}" in problems
    assert "is not the catalog's" in problems  # the SHA-256
    assert catalog_main(["verify", "--catalog", catalog_url]) == 1
    out = capsys.readouterr().out
    assert "FAIL  orig" in out and "0 match the catalog, 1 do not" in out


def test_a_session_not_in_the_catalog_fails_the_anchor(recorded, tmp_path):
    original, _ = recorded
    url = f"sqlite:///{tmp_path / 'empty.sqlite'}"
    crossfield.catalog.open(url).close()
    report = audit_with_catalog(original / "session.mcap", make_plugin_manager(), url, reproduce=False)
    assert not report.seal["passed"] and "session orig is not in the catalog" in report.seal["problems"][-1]


def test_a_seal_signed_by_another_key_fails_against_the_catalog(tmp_path):
    """Same file, same head, but the sidecar's signature replaced by another key's signature
    of the same statement: the catalog kept the station's, so the anchor names it."""
    import json

    from crossfield.catalog.anchor import check_row
    from crossfield.catalog.ingest import key_fingerprint
    from crossfield.catalog.synthetic import write_session
    from crossfield.recording import seal

    station, _, station_hex = seal.generate_key(tmp_path / "station.key")
    other, _, other_hex = seal.generate_key(tmp_path / "other.key")
    folder = write_session(tmp_path, "signed", 1_796_298_450_000_000_000, {"L01": 300.0}, signing_key=station)
    url = f"sqlite:///{tmp_path / 'c.sqlite'}"
    with crossfield.catalog.open(url) as cat:
        cat.add(folder)
        row = cat.seal("signed")
        assert row["public_key"] == station_hex and row["public_key_fingerprint"] == key_fingerprint(station_hex)
        assert check_row({**row, "signature_json": json.dumps(row["signature"])}, cat.url)["passed"]
        sidecar_file = seal.sidecar_path(folder / "session.mcap")
        doc = json.loads(sidecar_file.read_text())
        doc["signature"] = seal.sign(seal.load_private_key(other), seal.seal_statement(doc["chain_head"],
                                                                                     doc["file_sha256"]))
        sidecar_file.write_text(json.dumps(doc))
        (result,) = [check_row(r, cat.url) for r in cat.seals()]
    assert not result["passed"]
    assert f"catalogued key {station_hex}, the seal's {other_hex}" in " ".join(result["problems"])
