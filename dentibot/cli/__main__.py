"""``python -m dentibot.cli``: the ``dentibot`` command."""

import sys

from dentibot.cli import main

sys.exit(main())
