"""neoslam-stream: NeoSLAM with a RatSLAM back end, as a multiprocess zenoh pipeline or in-process.

Layout (one package, three layers):

* ``neoslam_stream.algorithms``: WHAT is computed. Plain classes with explicit pydantic configs,
  no transport, no processes (A features, B projector, C neocortex, D spatial-view cells, RatSLAM),
  composed into two cores, ``FrontEnd`` (A -> D) and ``BackEnd``. They import nothing of the runtime.
* ``neoslam_stream.runtime``: HOW data moves and is measured (codec, zenoh bus, workers,
  supervisor, monitor, checkpoints). It knows no algorithm.
* ``neoslam_stream.nodes``: between them. Each node turns the messages of its typed topics into
  calls on the algorithms; the recorder node writes the run folder; ``nodes.pipelines`` names
  which nodes a run hosts.

``NeoSLAM`` / ``RatSLAM`` (``neoslam_stream.api``) call the two cores in your process, no zenoh;
``neoslam run`` hosts the nodes in one process per stage.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"
__all__ = ["NeoSLAM", "RatSLAM", "StepResult", "__version__", "load_config"]


def __getattr__(name: str) -> Any:
    # lazy: `import neoslam_stream.runtime...` in a worker must not load every algorithm
    if name in ("NeoSLAM", "RatSLAM", "StepResult"):
        from . import api

        return getattr(api, name)
    if name == "load_config":
        from .config import load_config

        return load_config
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
