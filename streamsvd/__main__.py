"""``python -m streamsvd`` runs the command line."""

import sys

from streamsvd.cli import main

sys.exit(main())
