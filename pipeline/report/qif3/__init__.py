"""The official QIF 3.0.0 XML schemas (ISO 23952), unmodified, Boost Software License 1.0 (LICENSE.md);
used by :mod:`crossfield.report.qif_schema`. Their origin: README.md."""
