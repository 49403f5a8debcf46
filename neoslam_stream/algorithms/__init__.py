"""The algorithms, WHAT is computed: plain classes, each with one pydantic config passed whole.

No transport, no processes; nothing here imports ``neoslam_stream.runtime``, ``.nodes`` or zenoh
(tests/test_architecture.py). Files: only their own state and ``weights`` (weight files, ``.bin``).
``backbones`` imports torch; ``features``, ``projector``, ``projection``, ``weights`` only when used.

* ``frontend``  FrontEnd: A -> B -> C -> D, image -> template id, loop closure (arrays in and out)
* ``features`` (A, with ``backbones``, ``weights``)       image -> feature vector
* ``projector``, ``projection`` (B)                        features -> sLSBH bits (matrix, kernels)
* ``neocortex``, ``temporal_memory`` (+ ``_kernels``) (C)  bits -> winner cells (HTM Temporal Memory)
* ``spatial_view`` (D), ``interval_index`` (+ two kernel modules)  SDR -> template id, loop closure
* ``sequence``, ``oracle``  a sequence filter over D's closures; templates from ground truth
* ``backend``   BackEnd: yaw bias, odometry gate, pose cells, experience map
* ``ratslam``   PoseCellNetwork, ExperienceMap, LocalViewCells, VisualOdometry, YawBiasEstimator, ...
* ``errors``, ``_config``   InvalidInput; building a config from a model, a dict or keywords
"""
