"""The studies' own tests (``.venv/bin/python -m pytest studies/tests``; not part of ``make test``,
whose tests are tests/): studies/ on ``sys.path`` (a study's ``import _paths`` then adds the package
and bench/), and tests/ for the helpers a study's test shares with the product's tests."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
for path in (ROOT / "tests", ROOT / "studies"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))
