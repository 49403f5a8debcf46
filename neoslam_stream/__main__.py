"""``python -m neoslam_stream ...`` is ``neoslam ...``."""

import sys

from .cli import main

sys.exit(main())
