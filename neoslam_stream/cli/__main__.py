"""``python -m neoslam_stream.cli ...`` is ``neoslam ...``."""

import sys

from . import main

sys.exit(main())
