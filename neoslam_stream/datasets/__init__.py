"""Loaders of the real data sets used by the tests and benches (Nordland, TU Chemnitz corridor).

The data is not shipped: it lies in ``$NEOSLAM_DATA`` or, in a clone of the repository, in
``../shared/data`` next to it (see that folder's README for sources and licences).
"""

from __future__ import annotations

import os
from pathlib import Path


def data_root() -> Path:
    """``$NEOSLAM_DATA``, else ``<repository>/../shared/data``."""
    env = os.environ.get("NEOSLAM_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data"
