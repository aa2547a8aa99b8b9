"""`python -m jaxlens ...`: the `jaxlens` command."""

import sys

from .cli import main

sys.exit(main())
