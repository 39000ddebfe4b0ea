"""`python -m thermojax ...`: the same as the `thermojax` command."""

import sys

from .cli import main

sys.exit(main())
