"""Frame sources: where camera frames, odometry and ground truth come from.

A source is a plain iterator of :class:`~neoslam_stream.sources.base.SourceFrame`; the runtime's
source runner (``runtime.source_runner``) publishes what it yields. ``SOURCES`` names the built-in
kinds for ``--source KIND``; ``"package.module:Class"`` names a user's own.
"""

from __future__ import annotations

#: source kind -> "module:factory"
SOURCES: dict[str, str] = {
    "emulated": "neoslam_stream.runtime.emulated:EmulatedSource",
    "synthetic": "neoslam_stream.sources.synthetic:SyntheticWorldSource",
    "folder": "neoslam_stream.sources.files:ImageFolderSource",
    "video": "neoslam_stream.sources.files:VideoSource",
    "bag": "neoslam_stream.sources.bag:BagSource",
    "zenoh-ros2": "neoslam_stream.sources.zenoh_camera:ZenohRos2CameraSource",
    "zenoh": "neoslam_stream.sources.zenoh_camera:ZenohImageSource",
    "rmw-zenoh": "neoslam_stream.sources.rmw_zenoh:RmwZenohCameraSource",
}


def source_factory(kind: str) -> str:
    """The factory path of a source kind (a built-in name, or ``package.module:Class``)."""
    if ":" in kind:  # a user's own source class
        return kind
    try:
        return SOURCES[kind]
    except KeyError:
        raise ValueError(f"unknown source kind {kind!r}; known: {sorted(SOURCES)} "
                         f"(or 'package.module:Class')") from None
