"""``python -m crossfield.schemas [DIR]``: write the input files' JSON Schemas
(``<name>.schema.json``) to DIR, default beside :mod:`crossfield.schemas` (the checked-in copies)."""

from __future__ import annotations

import sys

from crossfield.schemas import write

if __name__ == "__main__":
    for path in write(sys.argv[1] if len(sys.argv) > 1 else None):
        print(f"wrote {path}")
