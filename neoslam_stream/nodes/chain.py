"""NeoSLAM's front end, A -> B -> C -> D, declared once.

Each :class:`ChainStage` names a stage, the topic it takes and the topic it gives, the method of
the :class:`~neoslam_stream.algorithms.frontend.FrontEnd` core that computes it and the config
sections that method reads. Everything that strings the stages together is derived from this
one declaration: the pipeline plan hosts one node per stage (``nodes/pipelines.py``), each node is
a shell that decodes its topic, calls :func:`run_stage` on its own core and encodes the result
(``nodes/frontend.py``), and the in-process API calls :func:`run_stage` for every stage in turn
(``api.py``) on one core.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from ..algorithms.frontend import FrontEnd, FrontEndConfig
from .topics import BIN_FEATURES, IMAGE, SDR, VISUAL_FEATURES, VISUAL_TEMPLATE, Topic


@dataclass(frozen=True)
class ChainStage:
    """One stage of the chain: ``call`` is the FrontEnd method, ``sections`` the config sections
    that are its node's parameters (``FrontEndConfig`` fields), ``parts`` the FrontEnd parts it
    builds. ``batched``: one call takes a whole batch of frames (cheaper per frame than one by one);
    else one call per frame, with the frame's stamp when ``stamped``."""

    name: str
    takes: Topic
    gives: Topic
    call: str
    sections: tuple[str, ...]
    parts: tuple[str, ...]
    batched: bool = False
    stamped: bool = False


#: A: camera frames -> CNN features
A = ChainStage("A", IMAGE, VISUAL_FEATURES, "features", ("features",), ("extractor",), batched=True)
#: B: features -> sLSBH bits (512 of 2048)
B = ChainStage("B", VISUAL_FEATURES, BIN_FEATURES, "codes", ("projector",), ("projector",), batched=True)
#: A and B in one stage on a torch device, so that only bits leave it
A_WITH_B = ChainStage("A", IMAGE, BIN_FEATURES, "codes_on_device", ("features", "projector"),
                      ("extractor", "torch_projection"), batched=True)
#: C: bits -> the Temporal Memory's winner cells (one learning step per frame)
C = ChainStage("C", BIN_FEATURES, SDR, "winner_cells", ("neocortex",), ("neocortex",))
#: D: winner cells -> visual template, loop closure
D = ChainStage("D", SDR, VISUAL_TEMPLATE, "template_of", ("spatial_view", "platform"), ("spatial_view",),
               stamped=True)


def neoslam_chain(config: FrontEndConfig) -> tuple[ChainStage, ...]:
    """The stages for a resolved front-end config: A, B, C, D, or A and B fused where B runs on
    a torch device (``projector.device`` not cpu)."""
    return (A, B, C, D) if config.projector.device == "cpu" else (A_WITH_B, C, D)


def run_stage(core: FrontEnd, stage: ChainStage, inputs: Sequence[Any], stamps: Sequence[float]) -> list[Any]:
    """``stage`` on frames whose inputs (what ``stage.takes`` carries, decoded) and stamps are
    given: one result per frame, in order."""
    call = getattr(core, stage.call)
    if stage.batched:
        return list(call(inputs)) if len(inputs) else []
    if stage.stamped:
        return [call(x, s) for x, s in zip(inputs, stamps, strict=True)]
    return [call(x) for x in inputs]
