"""Where a study finds the package and the bench protocols, and where it writes.

Every study imports this module first (``import _paths``), which works when it is run from the
repository root as ``python studies/X.py`` (the script's folder is on ``sys.path``). It puts the
repository root (the package) and bench/ (the protocols: bench_settings, nordland, tuc_corridor,
streams, timing, and the kept benches a study builds on, such as generalisation) on ``sys.path``.
A study may import bench/; bench/ never imports a study.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "studies"
#: what the studies wrote (studies/results/), beside bench/results/ of the benches
RESULTS = STUDIES / "results"
#: the studies' own settings files (studies/settings/), beside bench/settings/ of the protocols
SETTINGS = STUDIES / "settings"

for _path in (ROOT / "bench", ROOT):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))
