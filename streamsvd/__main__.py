"""``python -m streamsvd`` runs the command line."""

from streamsvd.cli import console

console()
