"""Every Zenoh key expression of triscan, built and parsed in one place.

Data flows on ``<prefix>/<robot_id>/<topic>`` (README, "The loop"); each service also announces itself
with a liveliness token on ``triscan/@health/<service>/<instance>`` and publishes JSON counters on
``triscan/@stats/<service>/<instance>``. Building and parsing all of them here keeps publishers,
subscribers, the launcher, ``triscan status`` and the access-control rules of the secure mode from
drifting apart, and validating the robot id here means a malformed id (one containing ``/`` or a
Zenoh wildcard) can never silently turn a publication key into a pattern that matches, or leaks
into, another robot's traffic.
"""

from __future__ import annotations

import re
from typing import Final

PREFIX: Final[str] = "triscan"

ROBOT_ID_PATTERN: Final[str] = r"[A-Za-z0-9_-]+"
"""One Zenoh key chunk made only of characters that carry no key-expression meaning."""

ROBOT_ID_MAX_LEN: Final[int] = 64
"""Bounded so that an id arriving from the network cannot bloat logs, metrics labels or keys."""

SCAN: Final[str] = "scan"
TENSOR: Final[str] = "tensor"
DETECTIONS: Final[str] = "detections"
TRUTH: Final[str] = "truth"
TRACKS: Final[str] = "tracks"
TOPICS: Final[tuple[str, ...]] = (SCAN, TENSOR, DETECTIONS, TRUTH, TRACKS)

_CHUNK_RE: Final[re.Pattern[str]] = re.compile(ROBOT_ID_PATTERN)


def validate_robot_id(robot_id: str) -> str:
    """Return ``robot_id`` unchanged if it is usable as exactly one key chunk, else raise ValueError.

    A non-str raises TypeError: that is a programming error, not bad data.

    fullmatch (not match with ``$``) is used on purpose: ``$`` would accept a trailing newline.
    """
    if not isinstance(robot_id, str):
        raise TypeError(f"robot_id must be a str, got {type(robot_id).__name__}")
    if len(robot_id) > ROBOT_ID_MAX_LEN:
        raise ValueError(f"robot_id is {len(robot_id)} characters long, the limit is {ROBOT_ID_MAX_LEN}")
    if _CHUNK_RE.fullmatch(robot_id) is None:
        raise ValueError(
            f"robot_id {robot_id!r} is not one key chunk: use only letters, digits, '_' and '-' "
            "(no '/', no wildcards, not empty)"
        )
    return robot_id


def _validate_prefix(prefix: str) -> str:
    """Check a deployment prefix; it may span several chunks (``site1/triscan``) but holds no wildcards."""
    if not isinstance(prefix, str) or not prefix:
        raise ValueError("key prefix must be a non-empty str")
    for chunk in prefix.split("/"):
        if _CHUNK_RE.fullmatch(chunk) is None:
            raise ValueError(
                f"key prefix {prefix!r} has an invalid chunk {chunk!r}: chunks use only letters, "
                "digits, '_' and '-'"
            )
    return prefix


def _validate_topic(topic: str) -> str:
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r}; known topics: {', '.join(TOPICS)}")
    return topic


def _key(robot_id: str, topic: str, prefix: str) -> str:
    return f"{_validate_prefix(prefix)}/{validate_robot_id(robot_id)}/{topic}"


def scan_key(robot_id: str, *, prefix: str = PREFIX) -> str:
    """Key on which the LiDAR (or simulator) of ``robot_id`` publishes its scans."""
    return _key(robot_id, SCAN, prefix)


def tensor_key(robot_id: str, *, prefix: str = PREFIX) -> str:
    """Key on which the encoder publishes stacked three-scan tensors for ``robot_id``."""
    return _key(robot_id, TENSOR, prefix)


def detections_key(robot_id: str, *, prefix: str = PREFIX) -> str:
    """Key on which the detector publishes detections for ``robot_id``."""
    return _key(robot_id, DETECTIONS, prefix)


def truth_key(robot_id: str, *, prefix: str = PREFIX) -> str:
    """Key on which the simulator publishes ground truth for ``robot_id``."""
    return _key(robot_id, TRUTH, prefix)


def tracks_key(robot_id: str, *, prefix: str = PREFIX) -> str:
    """Key on which the tracker publishes the tracks of ``robot_id``."""
    return _key(robot_id, TRACKS, prefix)


def wildcard_key(topic: str, *, prefix: str = PREFIX) -> str:
    """Key expression matching ``topic`` for every robot, so one service can serve a whole fleet."""
    _validate_topic(topic)
    return f"{_validate_prefix(prefix)}/*/{topic}"


ALL_SCANS: Final[str] = wildcard_key(SCAN)
ALL_TENSORS: Final[str] = wildcard_key(TENSOR)
ALL_DETECTIONS: Final[str] = wildcard_key(DETECTIONS)
ALL_TRUTH: Final[str] = wildcard_key(TRUTH)
ALL_TRACKS: Final[str] = wildcard_key(TRACKS)


def parse_key(key: str, *, prefix: str = PREFIX) -> tuple[str, str]:
    """Split a concrete key into ``(robot_id, topic)``.

    Subscribers on a wildcard learn which robot a sample came from only through its key, so a key
    that does not have exactly the expected shape is rejected rather than guessed at.
    """
    if not isinstance(key, str):
        raise TypeError(f"key must be a str, got {type(key).__name__}")
    head = _validate_prefix(prefix) + "/"
    if not key.startswith(head):
        raise ValueError(f"key {key!r} does not start with {head!r}")
    parts = key[len(head) :].split("/")
    if len(parts) != 2:
        raise ValueError(f"key {key!r} is not of the form {head}<robot_id>/<topic>")
    robot_id, topic = parts
    if topic not in TOPICS:
        raise ValueError(f"key {key!r} has unknown topic {topic!r}; known topics: {', '.join(TOPICS)}")
    try:
        validate_robot_id(robot_id)
    except ValueError as exc:
        raise ValueError(f"key {key!r}: {exc}") from None
    return robot_id, topic


# --- service keys: liveliness tokens and counters ---------------------------------------------------

HEALTH: Final[str] = "@health"
STATS: Final[str] = "@stats"
SHARDS: Final[str] = "@shards"
SOURCES: Final[str] = "@sources"
HEALTH_PREFIX: Final[str] = f"{PREFIX}/{HEALTH}"  # liveliness tokens: triscan/@health/<service>/<instance>
STATS_PREFIX: Final[str] = f"{PREFIX}/{STATS}"  # JSON counters: triscan/@stats/<service>/<instance>
ALL_HEALTH: Final[str] = f"{HEALTH_PREFIX}/**"
ALL_STATS: Final[str] = f"{STATS_PREFIX}/**"
# Liveliness tokens of the processes that share a fleet: triscan/@shards/<service>/<member>. The member is
# the process's Zenoh id, unique across hosts (a pid is not: every container's first process is 1).
SHARDS_PREFIX: Final[str] = f"{PREFIX}/{SHARDS}"
# Liveliness tokens of whoever publishes a topic for a robot: triscan/@sources/<topic>/<robot>/<source>. The
# source is the publisher's Zenoh id, so two encoders that both hold a robot's tensors for a moment (an
# encoder handover) hold two tokens, and the robot stays announced until the last one goes.
SOURCES_PREFIX: Final[str] = f"{PREFIX}/{SOURCES}"


def health_key(service: str, instance: str) -> str:
    """Liveliness token of one running service; the launcher watches :data:`ALL_HEALTH`."""
    return f"{HEALTH_PREFIX}/{validate_robot_id(service)}/{validate_robot_id(instance)}"


def service_health_key(service: str) -> str:
    """The health tokens of every instance of one service (``triscan/@health/detector/*``)."""
    return f"{HEALTH_PREFIX}/{validate_robot_id(service)}/*"


def stats_key(service: str, instance: str) -> str:
    """Where one running service publishes its counters."""
    return f"{STATS_PREFIX}/{validate_robot_id(service)}/{validate_robot_id(instance)}"


def service_stats_key(service: str) -> str:
    """The counters of every instance of one service (``triscan/@stats/detector/*``)."""
    return f"{STATS_PREFIX}/{validate_robot_id(service)}/*"


def shard_key(service: str, member: str) -> str:
    """Liveliness token of one process of ``service`` taking its share of the robots."""
    return f"{SHARDS_PREFIX}/{validate_robot_id(service)}/{validate_robot_id(member)}"


def shard_members_key(service: str) -> str:
    """Every live member of one service's shard set (``triscan/@shards/detector/*``)."""
    return f"{SHARDS_PREFIX}/{validate_robot_id(service)}/*"


def source_key(topic: str, robot_id: str, source: str) -> str:
    """Liveliness token of one publisher of ``topic`` for ``robot_id``: subscribers that serve only some
    robots (the detector processes sharing a fleet) subscribe to a robot's key once it is announced."""
    _validate_topic(topic)
    return f"{SOURCES_PREFIX}/{topic}/{validate_robot_id(robot_id)}/{validate_robot_id(source)}"


def topic_sources_key(topic: str) -> str:
    """Every announced source of ``topic``, all robots (``triscan/@sources/tensor/*/*``)."""
    _validate_topic(topic)
    return f"{SOURCES_PREFIX}/{topic}/*/*"


def _parse_service_key(key: str, prefix: str, what: str) -> tuple[str, str]:
    head = prefix + "/"
    if not isinstance(key, str) or not key.startswith(head) or key.count("/") != prefix.count("/") + 2:
        raise ValueError(f"{key!r} is not a triscan {what} key ({head}<service>/<instance>)")
    service, instance = key[len(head) :].split("/")
    return service, instance


def parse_health_key(key: str) -> tuple[str, str]:
    """``triscan/@health/<service>/<instance>`` → (service, instance)."""
    return _parse_service_key(key, HEALTH_PREFIX, "health")


def parse_stats_key(key: str) -> tuple[str, str]:
    """``triscan/@stats/<service>/<instance>`` → (service, instance)."""
    return _parse_service_key(key, STATS_PREFIX, "stats")


def parse_shard_key(key: str) -> tuple[str, str]:
    """``triscan/@shards/<service>/<member>`` → (service, member)."""
    return _parse_service_key(key, SHARDS_PREFIX, "shard")


def parse_source_key(key: str) -> tuple[str, str, str]:
    """``triscan/@sources/<topic>/<robot>/<source>`` → (topic, robot, source)."""
    head = SOURCES_PREFIX + "/"
    parts = key[len(head) :].split("/") if isinstance(key, str) and key.startswith(head) else []
    if len(parts) != 3 or parts[0] not in TOPICS:
        raise ValueError(f"{key!r} is not a triscan source key ({head}<topic>/<robot_id>/<source>)")
    topic, robot_id, source = parts
    try:
        validate_robot_id(robot_id)
        validate_robot_id(source)
    except ValueError as exc:
        raise ValueError(f"source key {key!r}: {exc}") from None
    return topic, robot_id, source


# --- access-control patterns of the secure mode (security/zenoh_config.py) --------------------------


def everything_key(prefix: str = PREFIX) -> str:
    """All triscan traffic of a deployment: data, health and stats."""
    return f"{_validate_prefix(prefix)}/**"


def service_keys(prefix: str = PREFIX) -> tuple[str, str]:
    """(health pattern, stats pattern) of a deployment's prefix."""
    base = _validate_prefix(prefix)
    return f"{base}/{HEALTH}/**", f"{base}/{STATS}/**"


def shard_keys(prefix: str = PREFIX) -> str:
    """The shard tokens of a deployment's prefix (``@`` chunks are matched by no wildcard)."""
    return f"{_validate_prefix(prefix)}/{SHARDS}/**"


def source_keys(prefix: str = PREFIX) -> str:
    """The source tokens of a deployment's prefix (``triscan/@sources/**``)."""
    return f"{_validate_prefix(prefix)}/{SOURCES}/**"
