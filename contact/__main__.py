"""``python -m contact billet --out DIR``."""

import sys

from .cli import main

sys.exit(main())
