"""The nodes of NeoSLAM's front end: one shell per stage of ``nodes/chain.py`` around its core.

Each node builds a :class:`~neoslam_stream.algorithms.frontend.FrontEnd` from its stage's config
sections (its parameters, resolved by the plan), which builds only that stage's parts; per batch
of messages it decodes what its topic carries (:meth:`FrontEndNode.take`), calls
:func:`~neoslam_stream.nodes.chain.run_stage` and makes one message per frame of the results
(:meth:`FrontEndNode.give`). A frame that ``frame_stride`` removes is counted (``strided``) and
gives nothing. Bad input raises the algorithms' ``InvalidInput``, which the worker counts and skips.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..algorithms.errors import InvalidInput
from ..algorithms.frontend import FrontEnd, FrontEndConfig
from ..algorithms.records import BinaryCode, WinnerCells
from ..runtime.messages import Message
from ..runtime.node import Node, Output
from .camera import decode_rgb
from .chain import A_WITH_B, A, B, C, ChainStage, D, run_stage
from .topics import IMAGE, record_data, record_of


class FrontEndNode(Node):
    """The shell of one chain stage (``stage``, set by each subclass)."""

    stage: ChainStage

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.inputs, cls.outputs, cls.batchable = (cls.stage.takes,), (cls.stage.gives,), cls.stage.batched

    def __init__(self, **sections: Any) -> None:
        super().__init__()
        self.core = FrontEnd(FrontEndConfig(**sections), resolve=False)

    def setup(self) -> None:
        self.core.warm_up(self.stage.parts)

    def warm_up(self, max_batch: int) -> None:
        if "extractor" in self.stage.parts:
            self.core.extractor.warm_up(max_batch)

    def process(self, topic: str, msg: Message) -> Output:
        return self.process_batch(topic, [msg])

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        kept = [m for m in msgs if self.stage.takes != IMAGE or self.core.keep(m.frame)]
        results = run_stage(self.core, self.stage, self.take(kept), [m.stamp for m in kept])
        # counted only once the batch succeeded: the worker retries a failed batch frame by frame
        self.counters["strided"] += len(msgs) - len(kept)
        return [(self.stage.gives, m.derive(self.stage.gives, self.give(r))) for m, r in zip(kept, results, strict=True)]

    def take(self, msgs: Sequence[Message]) -> Any:
        """The stage's input for these messages, decoded and checked."""
        raise NotImplementedError

    def give(self, result: Any) -> dict[str, Any]:
        """One frame's result as the data of the message the stage gives."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        return {p: getattr(self.core, p).state_dict() for p in self.stage.parts if p != "extractor"}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for p in self.stage.parts:
            if p != "extractor":
                getattr(self.core, p).load_state_dict(state[p])


def _frames(msgs: Sequence[Message]) -> list[np.ndarray]:
    return [decode_rgb(m.data) for m in msgs]


class FeatureNode(FrontEndNode):
    """A: ``image`` -> ``visual_features`` (the CNN's features and the backbone that ran)."""

    stage = A
    take = staticmethod(_frames)

    def give(self, result: np.ndarray) -> dict[str, Any]:
        return {"features": result, "backbone": self.core.extractor.backbone}

    def info(self) -> dict[str, Any]:
        if "extractor" not in self.core.__dict__:
            return {}
        x = self.core.extractor
        return {"backbone": x.backbone, "backbone_is_random": x.backbone == "random_alexnet",
                "weights": x.weights_source, "feature_dim": x.output_dim, "device": str(x.device),
                "frame_stride": self.core.config.features.frame_stride}


class ProjectorNode(FrontEndNode):
    """B: ``visual_features`` -> ``bin_features`` (sorted uint16 indices of 2048 bits, and the
    frame's int8 descriptor when B keeps one)."""

    stage = B

    def setup(self) -> None:
        try:  # B's BLAS threads, also where the process hosts other stages (monolithic)
            from threadpoolctl import threadpool_limits

            threadpool_limits(self.core.config.projector.threads)
        except ImportError:
            pass
        super().setup()

    def take(self, msgs: Sequence[Message]) -> np.ndarray:
        n = self.core.config.projector.input_dim
        feats = []
        for m in msgs:
            f = np.asarray(m["features"])
            if f.ndim != 1 or f.shape[0] != n:
                raise InvalidInput(f"features of shape {f.shape}, expected ({n},)")
            if not np.all(np.isfinite(f)):
                raise InvalidInput(f"features of frame {m.frame} contain NaN or infinite values")
            feats.append(f)
        return np.stack(feats)

    def give(self, result: BinaryCode) -> dict[str, Any]:
        return record_data(result)

    def info(self) -> dict[str, Any]:
        p = self.core.config.projector
        return {"projection": p.projection, "input_dim": p.input_dim,
                "matrix": p.matrix_path or f"generated (seed {p.seed})", "centre_window": p.centre_window}


class FusedFeatureNode(FeatureNode):
    """A and B on one torch device: ``image`` -> ``bin_features``; only the bits leave the device.
    The plan hosts it instead of A and B when ``projector.device`` is not cpu."""

    stage = A_WITH_B
    give = ProjectorNode.give

    def info(self) -> dict[str, Any]:
        out = super().info()
        if "torch_projection" in self.core.__dict__:
            p = self.core.config.projector
            out.update({"fused": "A+B on one device: only bits leave it", "projection": "gaussian (torch)",
                        "matrix_dtype": p.matrix_dtype, "centre_window": p.centre_window})
        return out


class NeocortexNode(FrontEndNode):
    """C: ``bin_features`` -> ``sdr`` (winner cells of 65536, the step's raw anomaly, and B's
    descriptor passed on)."""

    stage = C

    def take(self, msgs: Sequence[Message]) -> list[BinaryCode]:
        columns = self.core.config.neocortex.columns
        for m in msgs:
            if int(m["size"]) != columns:
                raise InvalidInput(f"bin_features of size {m['size']}, the neocortex has {columns} columns")
        return [record_of(BinaryCode, m.data) for m in msgs]

    def give(self, result: WinnerCells) -> dict[str, Any]:
        return record_data(result)

    def info(self) -> dict[str, Any]:
        n = self.core.neocortex
        return {"segments": n.tm.segments, "synapses": n.tm.synapses, "steps": n.steps,
                "mean_anomaly": n.anomaly_sum / n.steps if n.steps else None, "tie_break": n.config.tie_break}


class SpatialViewNode(FrontEndNode):
    """D: ``sdr`` -> ``visual_template`` (template id, loop-closure flag, best interval and its
    score, the runner-up interval and its score, the current interval). ``loop_closures`` counts
    this session's closures."""

    stage = D

    def __init__(self, **sections: Any) -> None:
        super().__init__(**sections)
        self.loops = 0

    def take(self, msgs: Sequence[Message]) -> list[WinnerCells]:
        return [record_of(WinnerCells, m.data) for m in msgs]

    def give(self, result: dict[str, Any]) -> dict[str, Any]:
        self.loops += bool(result["is_loop_closure"])
        # best_score as the algorithm gave it (an overlap count; a float when union_normalised):
        # templates.csv writes it unchanged
        return result

    def info(self) -> dict[str, Any]:
        d = self.core.spatial_view
        out = {**d.info(), "loop_closures": self.loops}
        if d.config.calibration.enabled:  # what the run settled on (report.json)
            out["calibration"] = d.calibration.report()
        return out

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "loops": self.loops}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.loops = int(state["loops"])

    def new_session(self) -> None:
        self.loops = 0
        self.core.spatial_view.new_session()


#: the node of each chain stage: the plan names ``neoslam_stream.nodes.frontend:make_node``
NODES = {s.call: n for s, n in ((A, FeatureNode), (B, ProjectorNode), (A_WITH_B, FusedFeatureNode),
                                (C, NeocortexNode), (D, SpatialViewNode))}


def make_node(call: str, **sections: Any) -> FrontEndNode:
    """The node of the chain stage whose core method is ``call``, with its config sections."""
    return NODES[call](**sections)
