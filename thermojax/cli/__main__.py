"""`python -m thermojax.cli ...`: the same as the `thermojax` command."""

import sys

from ._main import main

sys.exit(main())
