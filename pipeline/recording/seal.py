"""The seal of a recording: its chain head and SHA-256 outside the file, optionally signed.

At the end of every recorded run the recorder (the file sink) knows two
digests that a later reader cannot forge without being noticed somewhere
else:

* the **chain head**: the head of the integrity chain over every record of
  the file (:mod:`crossfield.recording.integrity`), as stated in the final
  ``/integrity`` record;
* the **file SHA-256**: of the finished file's bytes.

Both are printed by ``crossfield run``, written into ``report.json``
(``integrity.chain_head``, ``integrity.file_sha256``) and into a sidecar
``session.mcap.seal.json`` next to the recording. With a station key
(``[session] signing_key``, made by ``crossfield keygen``) they are signed
with Ed25519 (RFC 8032, the ``cryptography`` package): the final
``/integrity`` record holds a signature of the chain head (inside the file,
so it travels with it), the sidecar a signature of the chain head and the
file SHA-256. ``crossfield audit --expect-head HEX`` and ``--public-key
KEY`` check them. What each level proves: ``docs/replay-and-audit.md``.

Signed statements (UTF-8 text, exactly)::

    crossfield-seal/1\\nchain_head <64 hex>\\n                       (in the file)
    crossfield-seal/1\\nchain_head <64 hex>\\nfile_sha256 <64 hex>\\n  (in the sidecar)
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crossfield.errors import CrossfieldError

SEAL_FORMAT = "crossfield-seal/1"
#: The sidecar of ``session.mcap`` is ``session.mcap`` + this suffix.
SIDECAR_SUFFIX = ".seal.json"
ALGORITHM = "Ed25519"

_HEX64 = re.compile(r"^[0-9a-f]{64}$")


class SealError(CrossfieldError):
    """A key or a seal that cannot be read (the message names the file)."""


def sidecar_path(mcap_path: str | Path) -> Path:
    """``<recording>.seal.json`` next to the recording."""
    p = Path(mcap_path)
    return p.with_name(p.name + SIDECAR_SUFFIX)


def head_statement(chain_head: str) -> bytes:
    """The statement the in-file signature signs."""
    return f"{SEAL_FORMAT}\nchain_head {chain_head}\n".encode()


def seal_statement(chain_head: str, file_sha256: str) -> bytes:
    """The statement the sidecar signature signs."""
    return f"{SEAL_FORMAT}\nchain_head {chain_head}\nfile_sha256 {file_sha256}\n".encode()


def is_digest(text: Any) -> bool:
    """True for a lower-case 64-hex-digit SHA-256."""
    return isinstance(text, str) and bool(_HEX64.match(text))


# --------------------------------------------------------------------------
# Keys
# --------------------------------------------------------------------------


def generate_key(path: str | Path, *, overwrite: bool = False) -> tuple[Path, Path, str]:
    """Write a new Ed25519 station key: ``path`` (private key, PKCS#8 PEM, mode
    0600) and ``path.pub`` (public key, SubjectPublicKeyInfo PEM).
    Returns (private path, public path, public key hex)."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    private_path = Path(path)
    public_path = private_path.with_name(private_path.name + ".pub")
    for p in (private_path, public_path):
        if p.exists() and not overwrite:
            raise SealError(f"{p}: a file already exists there (not overwritten)")
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    try:
        fd = os.open(private_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(pem)
        public_path.write_bytes(
            key.public_key().public_bytes(
                serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
            )
        )
    except OSError as exc:
        raise SealError(f"{exc.filename or private_path}: cannot write the key: {exc.strerror}") from None
    return private_path, public_path, public_key_hex(key.public_key())


def load_private_key(path: str | Path) -> Any:
    """The Ed25519 private key in the PEM file ``path``."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise SealError(f"{path}: cannot read the signing key: {exc.strerror}") from None
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise SealError(f"{path}: not an unencrypted PEM private key ({exc})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SealError(f"{path}: not an Ed25519 key (crossfield signs with Ed25519)")
    return key


def load_public_key(spec: str | Path) -> Any:
    """An Ed25519 public key from a PEM file (``crossfield keygen``'s ``.pub``), a
    file holding the 64-hex-digit raw key, or the 64 hex digits themselves."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    text = str(spec).strip()
    if _HEX64.match(text.lower()) and not Path(text).exists():
        return Ed25519PublicKey.from_public_bytes(bytes.fromhex(text))
    try:
        data = Path(text).read_bytes()
    except OSError as exc:
        raise SealError(f"{text}: cannot read the public key: {exc.strerror}") from None
    stripped = data.strip().lower()
    if _HEX64.match(stripped.decode("ascii", "replace")):
        return Ed25519PublicKey.from_public_bytes(bytes.fromhex(stripped.decode()))
    try:
        key = serialization.load_pem_public_key(data)
    except (ValueError, TypeError) as exc:
        raise SealError(f"{text}: not a PEM public key nor 64 hex digits ({exc})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise SealError(f"{text}: not an Ed25519 public key")
    return key


def public_key_hex(public_key: Any) -> str:
    """The raw 32-byte public key as 64 hex digits."""
    from cryptography.hazmat.primitives import serialization

    return public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw).hex()


def sign(private_key: Any, statement: bytes) -> dict[str, str]:
    """``{"algorithm", "public_key", "value"}`` (hex) of an Ed25519 signature of ``statement``."""
    return {
        "algorithm": ALGORITHM,
        "public_key": public_key_hex(private_key.public_key()),
        "value": private_key.sign(statement).hex(),
    }


def signature_valid(public_key: Any, signature: Any, statement: bytes) -> bool:
    """True when ``signature`` (as :func:`sign` gives it) is ``public_key``'s signature of ``statement``."""
    from cryptography.exceptions import InvalidSignature

    if not isinstance(signature, dict) or signature.get("algorithm") != ALGORITHM:
        return False
    try:
        public_key.verify(bytes.fromhex(str(signature.get("value"))), statement)
    except (InvalidSignature, ValueError):
        return False
    return True


# --------------------------------------------------------------------------
# The sidecar
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Seal:
    """What leaves the file at the end of a run.

    chain_head / file_sha256: hex digests; signature: the sidecar's signature
    (None if unsigned); sidecar: where it was written.
    """

    recording: Path
    chain_head: str
    file_sha256: str
    signature: dict[str, str] | None = None
    sidecar: Path | None = None

    def to_json(self) -> dict[str, Any]:
        """The ``integrity`` section of report.json."""
        out: dict[str, Any] = {
            "format": SEAL_FORMAT,
            "recording": self.recording.name,
            "chain_head": self.chain_head,
            "file_sha256": self.file_sha256,
            "signed": self.signature is not None,
        }
        if self.signature is not None:
            out["signature"] = dict(self.signature)
        if self.sidecar is not None:
            out["sidecar"] = self.sidecar.name
        return out


def write_sidecar(seal: Seal) -> Path:
    """Write ``seal`` next to its recording; returns the sidecar's path."""
    path = sidecar_path(seal.recording)
    doc = seal.to_json()
    doc.pop("sidecar", None)
    try:
        path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise SealError(f"{path}: cannot write the seal: {exc.strerror}") from None
    return path


def read_sidecar(mcap_path: str | Path) -> dict[str, Any] | None:
    """The sidecar of a recording as data (None when there is none)."""
    path = sidecar_path(mcap_path)
    if not path.exists():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise SealError(f"{path}: not a readable seal: {exc}") from None
    if not isinstance(doc, dict):
        raise SealError(f"{path}: not a readable seal (not a JSON object)")
    return doc
