"""The whole configuration of a run: the runtime's sections plus every algorithm's, and the
configs that ship with the package (``neoslam_stream/configs/*.yaml``, read with
importlib.resources, so they work from a wheel and from any directory).

``load_config("default")`` (a shipped name), ``load_config("my.yaml")`` (a file) or
``load_config(None)`` (the models' defaults, which equal the paper's / reference code's values).

A config is applied on top of its ``base:`` (:func:`config_data`): a file that names none is
applied on top of the shipped ``default``, so a short file of one's own (``source:`` and
``platform:``) runs the main job on that source; ``base: none`` starts from the models' defaults.
The shipped configs say ``base: none``: each is complete on its own (``paper`` is frozen bit for
bit, the data sets' are the reference code's settings), and a copy of one keeps its meaning.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field, field_validator, model_validator

from .algorithms.backend import BackEndConfig, PoseCellStageConfig
from .algorithms.calibration import PlatformConfig
from .algorithms.features import FeatureConfig
from .algorithms.frontend import FrontEndConfig, LocalViewFrontEndConfig
from .algorithms.neocortex import NeocortexConfig
from .algorithms.oracle import OracleConfig
from .algorithms.projector import ProjectorConfig
from .algorithms.ratslam.experience_map import ExperienceMapConfig
from .algorithms.ratslam.visual_odometry import VisualOdometryConfig
from .algorithms.spatial_view import SpatialViewConfig
from .runtime.config import ConfigError, RunConfig, merge_config, parse_yaml_config, validate_config

__all__ = ["ConfigError", "DEFAULT_BASE", "FoxgloveConfig", "FullRunConfig", "Ros2OutConfig", "config_data",
           "config_model", "load_config", "packaged_configs", "packaged_config_text"]

#: what a config file that names no ``base:`` is applied on top of
DEFAULT_BASE = "default"


class Ros2OutConfig(BaseModel):
    """ROS 2 output (docs/ros2.md): the run's outputs as standard ROS 2 messages.

    ``format``: None (no live output), ``bridge`` (keys as zenoh-bridge-ros2dds), ``rmw`` (keys
    and attachments as rmw_zenoh) or ``both``; ``connect``: zenoh endpoints the publishing worker
    also connects to (the bridge's or rmw_zenoh's router, e.g. ``tcp/localhost:7447``). ``mcap``:
    the recorder also writes the same messages to ``outputs.mcap`` in the run folder."""

    model_config = {"extra": "forbid"}

    format: str | None = Field(None, pattern="^(bridge|rmw|both)$")
    domain_id: int = Field(0, ge=0, le=232)
    frame_id: str = "map"
    child_frame_id: str = "base_link"
    prefix: str = "/neoslam"
    distro: str = Field("jazzy", pattern="^(humble|jazzy|kilted)$")
    #: the path and the map markers are sent at most this often (seconds of source time)
    map_period_s: float = Field(1.0, gt=0)
    marker_scale: float = Field(0.1, gt=0)
    #: the path holds at most about this many poses (evenly thinned), so sending it stays cheap
    path_max_poses: int = Field(1000, ge=2)
    connect: list[str] = Field(default_factory=list)
    mcap: bool = True
    #: outputs.mcap holds the path and the map every this many seconds of source time
    mcap_map_period_s: float = Field(10.0, gt=0)

    def message_params(self) -> dict[str, Any]:
        """What :class:`~neoslam_stream.nodes.ros2_out.Ros2Messages` takes."""
        return {"frame_id": self.frame_id, "child_frame_id": self.child_frame_id, "prefix": self.prefix,
                "distro": self.distro, "map_period_s": self.map_period_s, "marker_scale": self.marker_scale,
                "path_max_poses": self.path_max_poses}


class FoxgloveConfig(BaseModel):
    """The run served to Foxglove (or Lichtblick) over the Foxglove WebSocket protocol
    (docs/foxglove.md), by a viewer process attached to the run like ``neoslam view``.

    ``listen``: ``HOST:PORT`` to serve on (None: not served; ``--foxglove`` sets it, loopback by
    default); the run's first frame waits up to ``wait_for_client_s`` for a client to subscribe
    (0: it does not wait), so that it sees the whole run; the camera at most ``image_hz`` frames a
    second, as JPEG of at most ``image_max_side`` pixels; while served, the experience map
    publishes its (relaxed) map at most every ``map_period_s`` of source time."""

    model_config = {"extra": "forbid"}

    listen: str | None = Field(None, pattern=r"^[^\s:]+:\d{1,5}$")
    wait_for_client_s: float = Field(30.0, ge=0)
    image_hz: float = Field(4.0, gt=0, le=60)
    image_max_side: int = Field(640, ge=32)
    jpeg_quality: int = Field(75, ge=10, le=100)
    map_period_s: float = Field(1.0, gt=0)
    #: the trajectory and ground-truth paths hold at most about this many poses (evenly thinned)
    path_max_poses: int = Field(2000, ge=2)
    #: messages buffered per client (the SDK's message_backlog_size): a slower client loses the oldest
    backlog: int = Field(1024, ge=16)


class FullRunConfig(RunConfig):
    """The runtime's sections plus every algorithm's (defaults = the paper's / reference code's)."""

    features: FeatureConfig = Field(default_factory=FeatureConfig)
    projector: ProjectorConfig = Field(default_factory=ProjectorConfig)
    neocortex: NeocortexConfig = Field(default_factory=NeocortexConfig)
    spatial_view: SpatialViewConfig = Field(default_factory=SpatialViewConfig)
    pose_cells: PoseCellStageConfig = Field(default_factory=PoseCellStageConfig)
    experience_map: ExperienceMapConfig = Field(default_factory=ExperienceMapConfig)
    local_view: LocalViewFrontEndConfig = Field(default_factory=LocalViewFrontEndConfig)
    visual_odometry: VisualOdometryConfig = Field(default_factory=VisualOdometryConfig)
    #: the oracle front end of `neoslam run --oracle-templates` (template ids from ground truth)
    oracle: OracleConfig = Field(default_factory=OracleConfig)
    #: wheel: odometry from the source; visual: RatSLAM's visual odometry stage
    odometry: str = Field("wheel", pattern="^(wheel|visual)$")
    ros2_out: Ros2OutConfig = Field(default_factory=Ros2OutConfig)
    foxglove: FoxgloveConfig = Field(default_factory=FoxgloveConfig)
    #: what you know about your robot and its world (speed, shortest loop, area): the physical
    #: quantities from which the calibrated decisions take their scales (docs/mapping.md)
    platform: PlatformConfig = Field(default_factory=PlatformConfig)

    @model_validator(mode="before")
    @classmethod
    def _derived_back_end(cls, data: Any) -> Any:
        """``pose_cells: derived`` / ``experience_map: derived``: the section from the platform's
        physical quantities (algorithms.backend.derived_back_end; docs/mapping.md)."""
        if not isinstance(data, dict) or "derived" not in (data.get("pose_cells"), data.get("experience_map")):
            return data
        from .algorithms.backend import derived_back_end

        platform = data.get("platform") or {}
        derived = derived_back_end(**PlatformConfig(**platform).model_dump()) if isinstance(platform, dict) else {}
        return {**data, **{k: derived[k] for k in ("pose_cells", "experience_map") if data.get(k) == "derived"}}

    @field_validator("source")
    @classmethod
    def _known_source_kind(cls, v: Any) -> Any:
        from .sources import check_kind  # the registry only: no source module is imported

        check_kind(v.kind)
        return v

    def front_end(self) -> FrontEndConfig:
        """The NeoSLAM front end's sections (the same objects, not copies)."""
        return FrontEndConfig.model_construct(features=self.features, projector=self.projector,
                                              neocortex=self.neocortex, spatial_view=self.spatial_view,
                                              platform=self.platform)

    def back_end(self) -> BackEndConfig:
        """The back end's sections (the same objects, not copies)."""
        return BackEndConfig.model_construct(pose_cells=self.pose_cells, experience_map=self.experience_map)


def config_model() -> type[BaseModel]:
    """The full run config model: the runtime's sections plus the algorithm sections."""
    return FullRunConfig


def _configs_dir() -> Any:
    return resources.files("neoslam_stream") / "configs"


def packaged_configs() -> list[str]:
    """Names of the configs that ship with the package (``default``, ``irat2011``, ...)."""
    return sorted(f.name[:-5] for f in _configs_dir().iterdir() if f.name.endswith(".yaml"))


def packaged_config_text(name: str) -> str:
    """The YAML text of a shipped config."""
    f = _configs_dir() / f"{name}.yaml"
    if not f.is_file():
        raise ConfigError(f"no shipped config named {name!r} (shipped: {', '.join(packaged_configs())})")
    return f.read_text()


def _config_text(path: str | Path, shipped_only: bool = False) -> tuple[str, str]:
    """(YAML text, origin) of a config file, or of a shipped config by name. A file of that name
    in the current directory wins over a shipped config (unless ``shipped_only``)."""
    p = Path(path)
    if p.is_file() and not shipped_only:
        return p.read_text(), str(p)
    name = p.stem if p.suffix == ".yaml" and p.parent == Path(".") else str(path)
    if (not p.suffix or p.suffix == ".yaml") and name in packaged_configs():
        return packaged_config_text(name), f"{name}.yaml (shipped with neoslam_stream)"
    raise ConfigError(f"config file {path} not found (shipped configs work by name too: "
                      f"{', '.join(packaged_configs())})")


def config_data(path: str | Path, _seen: tuple[str, ...] = (), _shipped: bool = False) -> tuple[dict[str, Any], str]:
    """(the mapping, origin) of a config with its ``base:`` resolved: the config applied on top of
    its base (``base: none``: on nothing, i.e. the models' defaults; no ``base:``: on
    :data:`DEFAULT_BASE`), a ``source.params`` of the base dropped when the config picks another
    source kind. A base is the name of a shipped config, or a YAML file (a path relative to the
    config that names it)."""
    text, origin = _config_text(path, _shipped)
    data = parse_yaml_config(text, origin)
    base = data.pop("base", DEFAULT_BASE)
    if base is None or base == "none":
        return data, origin
    if not isinstance(base, str):
        raise ConfigError(f"{origin}: base must name a shipped config, a YAML file or none, got {base!r}")
    is_file = base.endswith((".yaml", ".yml"))
    if is_file and not Path(base).is_absolute() and not _shipped:
        base = str(Path(str(path)).parent / base)
    elif not is_file and base not in packaged_configs():
        raise ConfigError(f"{origin}: base {base!r} is no shipped config ({', '.join(packaged_configs())}), "
                          f"no YAML file and not none")
    if base in (*_seen, str(path)):
        raise ConfigError(f"{origin}: base {base!r} comes back to itself ({' -> '.join((*_seen, str(path), base))})")
    under, _ = config_data(base, (*_seen, str(path)), not is_file)
    return merge_config(under, data), f"{origin} on {base}"


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None,
                model: type[BaseModel] | None = None) -> Any:
    """Load a YAML file, or a shipped config by name (``default``, ``irat2011``...), on top of its
    ``base:`` (:func:`config_data`), or the models' defaults when ``path`` is None; apply nested
    ``overrides``; validate."""
    model = model or config_model()
    if path is None:
        return validate_config({}, "(defaults)", model, overrides)
    data, origin = config_data(path)
    return validate_config(data, origin, model, overrides)
