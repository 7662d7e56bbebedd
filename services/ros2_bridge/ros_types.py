"""The ROS 2 message types the bridge speaks, and their CDR encoding, from one rosbags typestore per distro.

ROS 2 peers agree on a message by its *type hash* (RIHS01 since Iron; rmw_zenoh puts it in every data
key) and on its bytes by CDR with a 4-byte encapsulation header. Both follow from the message
definitions, so the bridge never writes a hash or a field layout down by hand: rosbags carries the
core definitions (``std_msgs``, ``sensor_msgs``, ``geometry_msgs``, ``visualization_msgs``) of each
distro, and the ``vision_msgs`` ones, which are not core, are registered from the upstream ``.msg``
files kept next to this module (``msg/vision_msgs/msg/*.msg``, vision_msgs 4.1 from the ROS 2 branch
as released for Humble and Jazzy; their RIHS01 hashes are checked against rosidl's in the tests).

Humble predates type hashes: rmw_zenoh on Humble puts the literal ``TypeHashNotSupported`` where
Jazzy puts ``RIHS01_<sha256>``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources
from typing import Final, Literal, get_args

from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

Distro = Literal["jazzy", "humble"]
DISTROS: Final[tuple[str, ...]] = get_args(Distro)
DEFAULT_DISTRO: Final[Distro] = "jazzy"

LASER_SCAN: Final[str] = "sensor_msgs/msg/LaserScan"
DETECTION3D_ARRAY: Final[str] = "vision_msgs/msg/Detection3DArray"
MARKER_ARRAY: Final[str] = "visualization_msgs/msg/MarkerArray"

TYPE_HASH_NOT_SUPPORTED: Final[str] = "TypeHashNotSupported"
"""What rmw_zenoh on Humble (no type description support) puts where Jazzy puts the RIHS01 hash."""

VISION_MSGS: Final[tuple[str, ...]] = (
    "ObjectHypothesis",
    "ObjectHypothesisWithPose",
    "BoundingBox3D",
    "Detection3D",
    "Detection3DArray",
)
VISION_MSGS_VERSION: Final[str] = "4.1 (ros-perception/vision_msgs, ROS 2 branch)"

CDR_HEADER_LE: Final[bytes] = b"\x00\x01\x00\x00"  # CDR_LE encapsulation, options 0
CDR_HEADER_BE: Final[bytes] = b"\x00\x00\x00\x00"  # CDR_BE

_STORES: Final[dict[str, Stores]] = {"jazzy": Stores.ROS2_JAZZY, "humble": Stores.ROS2_HUMBLE}


class CdrError(ValueError):
    """A payload that is not a CDR message of the expected type; ``reason`` is a metrics label."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def vision_msgs_definition(name: str) -> str:
    """The upstream ``.msg`` text of ``vision_msgs/msg/<name>``, as kept in the repository."""
    path = resources.files("services.ros2_bridge").joinpath("msg", "vision_msgs", "msg", f"{name}.msg")
    return path.read_text(encoding="utf-8")


def check_distro(distro: str) -> Distro:
    if distro not in DISTROS:
        raise ValueError(f"ROS distro must be one of {DISTROS}, got {distro!r}")
    return distro  # type: ignore[return-value]


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/LaserScan`` → ``sensor_msgs::msg::dds_::LaserScan_``, as rmw_zenoh names types."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@dataclass(frozen=True)
class RosTypes:
    """One distro's typestore, with vision_msgs registered, and what the wire needs from it."""

    distro: Distro
    store: Typestore

    def type_hash(self, typename: str) -> str:
        """What rmw_zenoh puts in the key for ``typename`` on this distro."""
        if self.distro == "humble":
            return TYPE_HASH_NOT_SUPPORTED
        return self.store.hash_rihs01(typename)

    def serialize(self, message: object, typename: str) -> bytes:
        """CDR (little-endian) with its 4-byte encapsulation header, as rmw_zenoh publishes."""
        return bytes(self.store.serialize_cdr(message, typename, little_endian=True))

    def deserialize(self, payload: bytes | memoryview, typename: str) -> object:
        """A message object, or CdrError (``not_cdr`` for a bad header, ``bad_cdr`` for a bad body)."""
        if len(payload) < 4 or bytes(payload[:2]) not in (CDR_HEADER_BE[:2], CDR_HEADER_LE[:2]):
            raise CdrError("not_cdr", f"{typename}: no CDR encapsulation header")
        try:
            return self.store.deserialize_cdr(payload, typename)
        except (SerdeError, IndexError, ValueError, OverflowError, MemoryError) as exc:
            raise CdrError("bad_cdr", f"{typename}: {' '.join(str(exc).split())}") from None

    def message(self, typename: str) -> type:
        """The generated dataclass of ``typename`` (build messages with it)."""
        return self.store.types[typename]


@functools.cache
def ros_types(distro: Distro = DEFAULT_DISTRO) -> RosTypes:
    """The typestore of ``distro`` with vision_msgs registered (built once per process and distro)."""
    store = get_typestore(_STORES[check_distro(distro)])
    types = {}
    for name in VISION_MSGS:
        types.update(get_types_from_msg(vision_msgs_definition(name), f"vision_msgs/msg/{name}"))
    store.register(types)
    return RosTypes(distro, store)
