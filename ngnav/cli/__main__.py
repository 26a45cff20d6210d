"""``python -m ngnav.cli``: the ``ngnav`` command."""

import sys

from ngnav.cli import main

sys.exit(main())
