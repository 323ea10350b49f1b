"""`python -m mogaf ...`: see mogaf.cli."""

import sys

from .cli import main

sys.exit(main())
