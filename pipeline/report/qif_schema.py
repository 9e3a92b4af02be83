"""Validation of QIF documents against the official QIF 3.0.0 XML schemas (ISO 23952).

The complete schema set of the Dimensional Metrology Standards Consortium
(QIFDocument.xsd, the application and library schemas) ships unmodified as
package data in ``crossfield/report/qif3/`` under its Boost Software License
(``LICENSE.md`` there). The schemas are compiled with lxml (libxml2) once per
process, offline.

QIFDocument.xsd imports the W3C XML-signature namespace from a remote address.
No component of QIF 3.0.0 refers to that namespace (its ``Signature`` element
is ``UserDataXMLType``; the local ``xmldsig-core-schema-qif3-namespace.xsd``
is the same schema moved into the QIF namespace, so it cannot stand for the
import), so the import is resolved to an empty schema of that namespace and
nothing is read from the network (``no_network``).
"""

from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

from lxml import etree

from crossfield.errors import CrossfieldError

__all__ = ["QIF_NAMESPACE", "QIF_VERSION", "QifValidationError", "qif_schema", "schema_dir", "validate_qif"]

#: The XML namespace of QIF 3 documents.
QIF_NAMESPACE = "http://qifstandards.org/xsd/qif3"
#: The schema version shipped (``versionQIF`` of the documents written).
QIF_VERSION = "3.0.0"

_XMLDSIG_NAMESPACE = "http://www.w3.org/2000/09/xmldsig#"
_EMPTY_XMLDSIG = (
    f'<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" targetNamespace="{_XMLDSIG_NAMESPACE}"/>'
).encode()


class QifValidationError(CrossfieldError):
    """A document does not follow the QIF 3.0.0 schema; the message names the file, line and schema message."""


class _OfflineResolver(etree.Resolver):
    """Resolves the remote xmldsig import to an empty schema of its namespace (see the module docstring)."""

    def resolve(self, url: str, pubid: str | None, context: Any) -> Any:
        if url.startswith(("http://", "https://")):
            if "xmldsig" in url:
                return self.resolve_string(_EMPTY_XMLDSIG, context)
            raise QifValidationError(f"QIF schema: unexpected remote schema {url} (no network use)")
        return None


def schema_dir() -> Path:
    """The folder of the shipped QIF 3.0.0 schemas (QIFDocument.xsd, LICENSE.md)."""
    return Path(str(resources.files("crossfield.report").joinpath("qif3")))


@lru_cache(maxsize=1)
def qif_schema() -> etree.XMLSchema:
    """The compiled QIF 3.0.0 schema (QIFDocument.xsd and everything it includes), cached."""
    parser = etree.XMLParser(no_network=True)
    parser.resolvers.add(_OfflineResolver())
    path = schema_dir() / "QIFDocument.xsd"
    return etree.XMLSchema(etree.parse(str(path), parser))


def validate_qif(document: etree._ElementTree | etree._Element | bytes | str | Path, where: str = "") -> None:
    """Raise :class:`QifValidationError` unless ``document`` is a valid QIF 3.0.0 document.

    document: a parsed tree or element, the XML bytes, or a path (str or Path) of a file.
    where: the name used in the message (default: the path, or ``<QIF document>``).
    The message is one line: ``<where>:<line>: <schema message>`` for the first
    violation, and how many more there are.
    """
    if isinstance(document, (str, Path)):
        where = where or str(document)
        try:
            tree = etree.parse(str(document), etree.XMLParser(no_network=True, resolve_entities=False))
        except OSError as exc:
            raise QifValidationError(f"{where}: cannot read the QIF document: {exc}") from None
        except etree.XMLSyntaxError as exc:
            raise QifValidationError(f"{where}: not well-formed XML: {exc}") from None
    elif isinstance(document, bytes):
        where = where or "<QIF document>"
        try:
            tree = etree.fromstring(document, etree.XMLParser(no_network=True, resolve_entities=False))
        except etree.XMLSyntaxError as exc:
            raise QifValidationError(f"{where}: not well-formed XML: {exc}") from None
    else:
        where = where or "<QIF document>"
        tree = document
    schema = qif_schema()
    if schema.validate(tree):
        return
    errors = list(schema.error_log)
    first = errors[0]
    more = f" ({len(errors) - 1} more)" if len(errors) > 1 else ""
    raise QifValidationError(f"{where}:{first.line}: QIF 3.0.0 schema: {first.message}{more}")
