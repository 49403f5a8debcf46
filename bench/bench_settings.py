"""Where the benches find their inputs: the data sets and the settings files in bench/settings/.

The data sets are not shipped: they lie in ``$NEOSLAM_DATA`` or, in a clone of the repository, in
``../shared/data`` next to it (that folder's README gives sources and licences); public sets a user
downloads (Gardens Point Walking) in ``$NEOSLAM_DATASETS`` or ``~/.cache/neoslam_stream/datasets``,
each with a SOURCE.md that gives its source and licence. A settings file
holds sections of a run's config (``spatial_view``, ``pose_cells`` ...), validated by the run
config's models so that a misspelt key fails, plus a ``protocol`` section for what the bench's
protocol decides itself (thresholds, what it resolves from the data).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import yaml

from neoslam_stream.config import ConfigError, load_config

SETTINGS = Path(__file__).resolve().parent / "settings"


def cache_key(obj: Any) -> str:
    """A short digest of ``obj`` (settings sections, config dumps: JSON with sorted keys) that names a
    bench's cached recording, so that a changed setting records anew instead of reusing another's."""
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def data_root() -> Path:
    """``$NEOSLAM_DATA``, else ``<repository>/../shared/data``."""
    env = os.environ.get("NEOSLAM_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def datasets_cache() -> Path:
    """``$NEOSLAM_DATASETS``, else ``~/.cache/neoslam_stream/datasets``: downloaded public data sets,
    one folder each (never copied into the repository)."""
    env = os.environ.get("NEOSLAM_DATASETS")
    return Path(env) if env else Path.home() / ".cache" / "neoslam_stream" / "datasets"


def check_sections(sections: dict[str, Any], origin: str) -> dict[str, Any]:
    """``sections`` (config sections, as in a run's YAML) unchanged once the run config's models
    accept them; otherwise a :class:`ConfigError` naming ``origin`` and the field."""
    try:
        load_config(None, sections)
    except ConfigError as exc:
        raise ConfigError(f"{origin}: {exc}") from None
    return sections


def read_settings(name: str) -> dict[str, Any]:
    """bench/settings/``name``.yaml as a dict, unchecked."""
    return yaml.safe_load((SETTINGS / f"{name}.yaml").read_text()) or {}


def load_settings(name: str) -> dict[str, Any]:
    """bench/settings/``name``.yaml as a dict; its sections other than ``protocol`` checked by
    :func:`check_sections`."""
    data = read_settings(name)
    check_sections({k: v for k, v in data.items() if k != "protocol"}, f"bench/settings/{name}.yaml")
    return data


def back_end_sections(name: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``pose_cells`` and ``experience_map`` sections of bench/settings/``name``.yaml: its own
    when it has them (the paper's settings), else the default's, derived from its ``platform``."""
    data = load_settings(name)
    if "pose_cells" in data:
        return data["pose_cells"], data["experience_map"]
    cfg = load_config("default", {"platform": data["platform"]})
    return cfg.pose_cells.model_dump(), cfg.experience_map.model_dump()
