"""`python -m scenesort.backend.commands ...`: the `scenesort` command (how the add-on starts
the bundled service)."""

import sys

from scenesort.backend.commands import main

sys.exit(main())
