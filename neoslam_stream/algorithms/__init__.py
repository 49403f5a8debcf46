"""The algorithms, WHAT is computed: plain classes, each with one pydantic config model passed
whole (``SpatialViewCells(SpatialViewConfig(...))``, or keyword overrides of its defaults).

No transport, no processes, no files except the explicit load/save of their own state; nothing
here imports ``neoslam_stream.runtime``, ``neoslam_stream.nodes`` or zenoh (a test checks it).
Only ``features``/``backbones`` import torch, and ``features`` only when an extractor is built.

* ``features``         A  VisualFeatureExtractor   image -> float32 feature vector
* ``projector``        B  BinaryProjector          features -> 512 sorted bits of 2048 (sLSBH)
* ``temporal_memory``  C  TemporalMemory           htm.core-equivalent Temporal Memory
* ``neocortex``        C  Neocortex                bits -> winner cells
* ``spatial_view``     D  SpatialViewCells         SDR -> template id, loop closure
* ``ratslam``             PoseCellNetwork, ExperienceMap, LocalViewCells, VisualOdometry
"""
