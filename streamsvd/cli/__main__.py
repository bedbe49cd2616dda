"""``python -m streamsvd.cli`` runs the command line."""

from streamsvd.cli import console

console()
