"""`python -m jaxlens ...`: the `jaxlens` command."""

from .cli import console

console()
