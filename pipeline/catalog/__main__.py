"""``python -m crossfield.catalog SUBCOMMAND ...`` (the same as ``crossfield catalog``)."""

import sys

from crossfield.catalog.commands import main

sys.exit(main())
