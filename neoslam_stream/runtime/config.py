"""The runtime's typed configuration (pydantic): run, bus, source; and the YAML loader.

One model per component; ``RunConfig`` composes the runtime's. Unknown keys are errors, and a bad
value gives one clear message naming the field (``ConfigError``). The algorithms' sections are
their own models; ``neoslam_stream.config`` composes everything (and checks the source kind
against the sources' registry, which the runtime does not know).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator


class ConfigError(ValueError):
    """A configuration file or value is invalid; the text names the field and the problem."""


class Strict(BaseModel):
    """A config section: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


#: input queue capacity of the runtime's own topics unless configured (see BusConfig.capacity); a
#: plan gives those of its nodes' topics and may give the image ring's (PipelinePlan.capacity),
#: which otherwise holds ``default_capacity`` frames
DEFAULT_CAPACITY = {"odom": 256, "groundtruth": 256}


class BusConfig(Strict):
    """zenoh transport. Every process of a run listens on its own loopback port (assigned
    automatically on ``host``) and connects to the others; ``listen``/``connect`` add endpoints,
    e.g. ``connect: [tcp/10.0.0.2:7447]`` for a zenoh router that links several hosts."""

    host: str = "127.0.0.1"
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=list)
    #: endpoints on which the supervisor's router alone also listens: the rendezvous of a run split
    #: over several hosts (docs/hosts.md); every other process stays on `host`
    router_listen: list[str] = Field(default_factory=list)
    #: zenoh shared memory for large payloads. Off: at camera rates it gains little per message and
    #: its first use in each process stalls the pipeline (docs/runtime.md)
    shm: bool = False
    #: a zenoh json5 config file for settings neoslam does not make itself (TLS certificates,
    #: access control; see docs/reliability.md); neoslam's endpoints, mode and scouting-off apply on top
    zenoh_config: str | None = None
    #: zenoh's transmit queue per link for data messages, in batches of 64 kB (None: zenoh's
    #: default, 2). With two, a real-time publisher drops a message whose batches a busy core does
    #: not send within zenoh's 1 ms (an image is 300 kB for the synthetic world's 416x240 frames);
    #: 16 (1 MB) holds three such frames or one 640x480 RGB frame (docs/runtime.md)
    tx_queue: int | None = Field(16, ge=1, le=64)
    #: input queue capacity per topic (real-time: ring, drop-oldest; lossless: FIFO, blocks); a
    #: topic named here overrides the plan's. odom and groundtruth: tiny, and path integration needs
    #: every one; image: the plan's (a batch before a batching stage) or ``default_capacity``
    #: (docs/runtime.md)
    capacity: dict[str, int] = Field(default_factory=lambda: dict(DEFAULT_CAPACITY))
    default_capacity: int = Field(2, ge=1)
    #: lossless mode: the source runs at most this many frames ahead of the final topic
    window: int = Field(8, ge=1)

    @field_validator("zenoh_config")
    @classmethod
    def _exists(cls, v: str | None) -> str | None:
        if v is not None and not Path(v).is_file():
            raise ValueError(f"zenoh config file {v} does not exist")
        return str(Path(v).resolve()) if v is not None else None

    @field_validator("capacity")
    @classmethod
    def _positive(cls, v: dict[str, int]) -> dict[str, int]:
        bad = {k: c for k, c in v.items() if c < 1}
        if bad:
            raise ValueError(f"capacities must be >= 1: {bad}")
        return {**DEFAULT_CAPACITY, **v}  # naming one topic keeps the others' defaults


class SourceConfig(Strict):
    """Where frames come from. ``kind`` names a source (a registered kind, or ``module:Class``)."""

    kind: str = "synthetic"
    params: dict[str, Any] = Field(default_factory=dict)
    #: auto: recorded timing for real-time runs of recorded data, as fast as possible when lossless
    pacing: Literal["auto", "fixed", "recorded", "asap"] = "auto"
    rate: float | None = Field(None, gt=0)
    rate_multiplier: float = Field(1.0, gt=0)
    max_frames: int | None = Field(None, ge=1)
    duration: float | None = Field(None, gt=0)
    #: camera.zip in the run folder (camera_log.py): a JPEG every this many seconds of source time
    #: (0: none), at most ``camera_log_frames`` of them (beyond: thinned evenly)
    camera_log_s: float = Field(0.5, ge=0)
    camera_log_frames: int = Field(600, ge=2)


class EmulatedConfig(Strict):
    """The paper's worked example: service times of the emulated stages (ms)."""

    tau_ms: list[float] = Field(default_factory=lambda: [50.0, 280.0, 20.0, 350.0])
    busy: bool = False


class RunSection(Strict):
    """How a run is hosted and kept: its pipeline, topology, mode, processes and checkpoints."""

    pipeline: str = "emulated"
    topology: Literal["pipeline", "monolithic"] = "pipeline"
    #: lossless: nothing dropped, source back-pressured; realtime: drop-oldest rings
    mode: Literal["lossless", "realtime"] = "lossless"
    out: str = "runs"
    name: str | None = None
    seed: int = 42
    #: threads per stage (torch/BLAS/numba); stages not named get 1
    threads: dict[str, int] = Field(default_factory=dict)
    #: scheduling niceness per process, 0-19 (higher: yields the CPU to the others; no privilege
    #: needed): keys are stage names as in ``threads``, "monolithic", "source" or "monitor"
    nice: dict[str, int] = Field(default_factory=dict)
    #: CPUs a process may run on (sched_setaffinity), keys as for ``nice``; not named: any CPU
    cpus: dict[str, list[int]] = Field(default_factory=dict)
    live: bool = True
    #: real-time mode: after the source ends, let frames in flight finish for this long
    drain_s: float = Field(2.0, ge=0)
    startup_timeout: float = Field(300.0, gt=0)
    max_restarts: int = Field(3, ge=0)
    max_batch: int = Field(8, ge=1)
    #: per batchable stage (keys are stage names, as in ``threads``): milliseconds it may wait for
    #: a second frame when it finds one alone, used only while frames come at least that often. A
    #: stage whose cost per frame falls with the batch (B reads its matrix once per batch) then
    #: spends less CPU per frame, for at most that much latency; not named: no wait
    batch_wait_ms: dict[str, float] = Field(default_factory=dict)
    log_level: str = "WARNING"
    #: save every stage's state every N source frames (0 = never); see docs/reliability.md
    checkpoint_every: int = Field(0, ge=0)
    #: the stage workers this host runs when a run is split over several hosts (None: all;
    #: ["rest"]: those no other host of the run announced); see runtime/share.py
    stages: list[str] | None = None
    #: the run id (key expressions neoslam/<run_id>/...): every host of a split run must use the same one
    run_id: str | None = Field(None, pattern=r"^[A-Za-z0-9_-]{1,64}$")
    #: a split run: another host silent this long (seconds) is gone, and this host ends its share
    host_timeout: float = Field(30.0, gt=0)
    #: a file to write every frame's path through the stages to, as a Chrome / Perfetto trace
    #: (runtime/trace.py; docs/performance.md); None: no trace
    trace: str | None = None
    #: tools attached to the run (by the name of their liveliness token ``alive/<name>``, e.g. the
    #: Foxglove viewer of ``neoslam run --foxglove``) that the first frame waits for, at most
    #: ``wait_for_s`` seconds (then the run starts without them, with a warning)
    wait_for: list[str] = Field(default_factory=list)
    wait_for_s: float = Field(30.0, ge=0)


    @field_validator("nice")
    @classmethod
    def _niceness(cls, v: dict[str, int]) -> dict[str, int]:
        bad = {k: n for k, n in v.items() if not 0 <= n <= 19}
        if bad:
            raise ValueError(f"niceness must lie in 0..19 (raising priority needs privileges): {bad}")
        return v

    @field_validator("batch_wait_ms")
    @classmethod
    def _waits(cls, v: dict[str, float]) -> dict[str, float]:
        bad = {k: w for k, w in v.items() if not (math.isfinite(w) and w >= 0)}
        if bad:
            raise ValueError(f"batch_wait_ms must be finite milliseconds >= 0: {bad}")
        return v

    @field_validator("cpus")
    @classmethod
    def _cpu_sets(cls, v: dict[str, list[int]]) -> dict[str, list[int]]:
        bad = {k: c for k, c in v.items() if not c or any(i < 0 for i in c)}
        if bad:
            raise ValueError(f"cpus must be non-empty lists of CPU numbers >= 0: {bad}")
        return v


class RunConfig(Strict):
    """The runtime's sections of a run's config (the type the runtime is given; the package's
    full config, with the algorithms' sections, subclasses it)."""

    run: RunSection = Field(default_factory=RunSection)
    bus: BusConfig = Field(default_factory=BusConfig)
    source: SourceConfig = Field(default_factory=lambda: SourceConfig(kind="emulated", params={"frames": None}))
    emulated: EmulatedConfig = Field(default_factory=EmulatedConfig)


def _format_error(exc: ValidationError, origin: str) -> str:
    faults = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "<root>"
        faults.append(f"{loc}: {err['msg']}")
    return f"invalid configuration {origin}: " + "; ".join(faults)


def parse_yaml_config(text: str, origin: str) -> dict[str, Any]:
    """The mapping a config's YAML ``text`` holds (empty text: an empty mapping); a fault is one
    :class:`ConfigError` naming ``origin``."""
    try:
        loaded = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{origin} is not valid YAML: {exc}") from None
    if not isinstance(loaded, dict):
        raise ConfigError(f"{origin} must hold a mapping at the top level")
    return loaded


def validate_config(data: dict[str, Any], origin: str, model: type[BaseModel],
                    overrides: dict[str, Any] | None = None) -> Any:
    """``data`` with nested ``overrides`` on top (:func:`merge_config`), validated against ``model``;
    any fault is one :class:`ConfigError` naming ``origin`` and the field."""
    if overrides:
        data = merge_config(data, overrides)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_error(exc, origin)) from None


def load_yaml_config(text: str | None, origin: str, model: type[BaseModel],
                     overrides: dict[str, Any] | None = None) -> Any:
    """Validate YAML ``text`` (None: the model's defaults) with nested ``overrides`` on top against
    ``model``; any fault is one :class:`ConfigError` naming ``origin`` and the field."""
    return validate_config({} if text is None else parse_yaml_config(text, origin), origin, model, overrides)


def merge_config(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """The config ``over`` applied on top of ``base`` (:func:`merge_dicts`), except that a
    ``source.params`` of ``base`` is dropped when ``over`` names another source kind: params belong
    to their kind (a synthetic world's ``seed`` means nothing to a folder source)."""
    return merge_dicts(_without_other_kinds_params(base, over), over)


def _without_other_kinds_params(data: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``data`` without its ``source.params`` when ``over`` picks another source kind."""
    src, new = data.get("source"), over.get("source")
    if not (isinstance(src, dict) and isinstance(new, dict) and "kind" in new):
        return data
    if src.get("kind", SourceConfig.model_fields["kind"].default) == new["kind"]:
        return data
    return {**data, "source": {k: v for k, v in src.items() if k != "params"}}


def merge_dicts(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` merged in, nested mappings merged key by key (neither is changed)."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge_dicts(out[k], v)
        else:
            out[k] = v
    return out
