"""Frame sources: where camera frames, odometry and ground truth come from.

A source is a plain iterator of :class:`~neoslam_stream.runtime.source.SourceFrame`; the runtime's
source process publishes what it yields. ``SOURCES`` names the built-in kinds for ``--source KIND``
(``"package.module:Class"`` names a user's own); ``launch`` resolves a run's kind to its factory
here and hands it to the runtime, which knows no source module. A live source (its class's
``live``) runs in real time unless the config or a flag names the mode (:func:`with_live_default`).
"""

from __future__ import annotations

from typing import Any

#: source kind -> "module:factory"
SOURCES: dict[str, str] = {
    "emulated": "neoslam_stream.runtime.emulated:EmulatedSource",
    "synthetic": "neoslam_stream.sources.synthetic:SyntheticWorldSource",
    "folder": "neoslam_stream.sources.files:ImageFolderSource",
    "video": "neoslam_stream.sources.files:VideoSource",
    "camera": "neoslam_stream.sources.camera:CameraSource",
    "bag": "neoslam_stream.sources.bag:BagSource",
    "zenoh-ros2": "neoslam_stream.sources.zenoh_camera:ZenohRos2CameraSource",
    "zenoh": "neoslam_stream.sources.zenoh_camera:ZenohImageSource",
    "rmw-zenoh": "neoslam_stream.sources.rmw_zenoh:RmwZenohCameraSource",
}

def with_live_default(cfg: Any) -> Any:
    """``cfg`` in real-time mode when its source is live and neither the config file nor a flag
    (``--lossless``) named ``run.mode``; else ``cfg`` itself. The DESIGN's rule (real time for live
    input, lossless for recorded data), applied where a run starts."""
    if "mode" in cfg.run.model_fields_set or not getattr(source_class(cfg.source.kind), "live", False):
        return cfg
    return cfg.model_copy(update={"run": cfg.run.model_copy(update={"mode": "realtime"})})


def check_kind(kind: str) -> str:
    """``kind`` when it names a built-in source or a user's class (``package.module:Class``);
    else a ValueError that lists the known kinds (the config's check of ``source.kind``)."""
    if ":" not in kind and kind not in SOURCES:
        raise ValueError(f"unknown source kind {kind!r}; known: {', '.join(sorted(SOURCES))} "
                         f"(or 'package.module:Class' for your own)")
    return kind


def source_factory(kind: str) -> str:
    """The factory path of a source kind (a built-in name, or ``package.module:Class``)."""
    return kind if ":" in check_kind(kind) else SOURCES[kind]


def source_class(kind: str) -> Any:
    """The factory (usually the class) of a source kind, imported; an import that fails is a
    :class:`~.params.SourceParamError` naming the kind."""
    from ..runtime.node import load_factory
    from .params import SourceParamError

    path = source_factory(kind)
    try:
        return load_factory(path)
    except (ImportError, AttributeError, ValueError) as exc:
        raise SourceParamError(f"source {kind}: cannot load {path}: {exc}") from None


def check_source(kind: str, params: dict[str, Any], files: bool = True) -> None:
    """Check a source's parameters before a run starts (sources/params.py): a
    :class:`~.params.SourceParamError` names an unknown parameter or a bad value in one line."""
    from .params import check_params

    check_params(source_class(kind), params, kind, files)


def gives_odometry(kind: str, params: dict[str, Any]) -> bool | None:
    """Whether the source gives odometry with its frames (its ``gives_odometry``), None when it
    does not say (a source of your own without that class method)."""
    ask = getattr(source_class(kind), "gives_odometry", None)
    return ask(**params) if callable(ask) else None
