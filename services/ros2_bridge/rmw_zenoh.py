"""How ROS 2 appears on Zenoh: data keys, sample attachments and graph tokens, in both bridge styles.

Two ways ROS 2 traffic reaches Zenoh, and the bridge speaks both (``--style``):

* **rmw_zenoh** (ROS 2 nodes running ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``): data on
  ``<domain>/<fully qualified topic without the leading slash>/<DDS type name>/<type hash>``, e.g.
  ``0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c1…``, the hash ``TypeHashNotSupported``
  on Humble. Every sample carries a 33-byte attachment, zenoh-ext serialisation of
  ``(int64 sequence_number, int64 source_timestamp, uint8[16] source_gid)``: 8 + 8 bytes
  little-endian, then the GID as a sequence, i.e. a LEB128 length byte (16) and 16 bytes
  (``rmw_zenoh_cpp/src/detail/attachment_helpers.cpp``). The ROS graph (``ros2 topic list``) is made of
  liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<namespace>/<node>/<topic>/
  <type>/<hash>/<qos>`` with ``/`` written ``%`` inside names (``liveliness_utils.cpp``).
* **ros2dds** (zenoh-bridge-ros2dds in front of DDS nodes): data on ``[<namespace>/]<topic>``, the
  same CDR payload, no attachment and no tokens of this kind.

Names follow ROS: a namespace is ``/`` (root) or ``/a/b``; a fully qualified topic is
``<namespace>/<topic>``. Everything here is pure string and byte work, so both styles are tested
without a network.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Final, Literal, get_args

Style = Literal["rmw_zenoh", "ros2dds"]
STYLES: Final[tuple[str, ...]] = get_args(Style)

ADMIN_SPACE: Final[str] = "@ros2_lv"
NODE: Final[str] = "NN"
PUBLISHER: Final[str] = "MP"
SUBSCRIPTION: Final[str] = "MS"
GID_SIZE: Final[int] = 16  # RMW_GID_STORAGE_SIZE
ATTACHMENT_SIZE: Final[int] = 8 + 8 + 1 + GID_SIZE
DEFAULT_QOS: Final[str] = "::,10:,:,:,,"
"""rmw_zenoh's QoS token for reliable, volatile, keep-last 10 (empty fields mean "the default")."""

_ATTACHMENT: Final[struct.Struct] = struct.Struct(f"<qqB{GID_SIZE}s")
_NAME_CHUNK: Final[re.Pattern[str]] = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_INT64_MAX: Final[int] = (1 << 63) - 1


class AttachmentError(ValueError):
    """An attachment that is not rmw_zenoh's (sequence number, timestamp, GID)."""


@dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33 bytes rmw_zenoh attaches to every published sample."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(gid)}")
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_SIZE, gid)


def decode_attachment(raw: bytes | None) -> Attachment:
    """Parse an rmw_zenoh attachment; AttachmentError if it is missing or has any other shape."""
    if raw is None:
        raise AttachmentError("no attachment (rmw_zenoh attaches one to every sample)")
    if len(raw) != ATTACHMENT_SIZE:
        raise AttachmentError(f"attachment of {len(raw)} bytes, rmw_zenoh's has {ATTACHMENT_SIZE}")
    seq, stamp, gid_len, gid = _ATTACHMENT.unpack(raw)
    if gid_len != GID_SIZE:
        raise AttachmentError(f"GID length byte is {gid_len}, expected {GID_SIZE}")
    return Attachment(seq, stamp, gid)


def check_style(style: str) -> Style:
    if style not in STYLES:
        raise ValueError(f"style must be one of {STYLES}, got {style!r}")
    return style  # type: ignore[return-value]


def normalize_namespace(namespace: str) -> str:
    """``""``, ``"/"`` → ``"/"``; ``"robot1"``, ``"/robot1/"`` → ``"/robot1"``; ValueError if no ROS name."""
    chunks = [c for c in namespace.strip("/").split("/") if c] if namespace else []
    if namespace.strip("/") and len(chunks) != namespace.strip("/").count("/") + 1:
        raise ValueError(f"namespace {namespace!r} has an empty segment")
    for chunk in chunks:
        if _NAME_CHUNK.fullmatch(chunk) is None:
            raise ValueError(f"namespace {namespace!r}: {chunk!r} is not a ROS name segment")
    return "/" + "/".join(chunks)


def check_topic(topic: str) -> str:
    """A relative ROS topic name (``scan``, ``sensors/scan``); ValueError otherwise."""
    chunks = topic.split("/")
    if not topic or any(_NAME_CHUNK.fullmatch(c) is None for c in chunks):
        raise ValueError(f"topic {topic!r} is not a relative ROS topic name")
    return topic


def qualified_topic(namespace: str, topic: str) -> str:
    """``("/robot1", "triscan/markers")`` → ``/robot1/triscan/markers``."""
    ns = normalize_namespace(namespace)
    return f"{ns.rstrip('/')}/{check_topic(topic)}"


def data_key(style: Style, domain: int, fq_topic: str, dds_type: str, type_hash: str) -> str:
    """Key of the samples of ``fq_topic`` in ``style``."""
    name = fq_topic.strip("/")
    if style == "ros2dds":
        return name
    return f"{domain}/{name}/{dds_type}/{type_hash}"


def subscription_key(style: Style, domain: int, namespace: str | None, topic: str, dds_type: str) -> str:
    """What to subscribe to for ``topic`` of one namespace, or of every one-segment namespace (None).

    rmw_zenoh style leaves the hash chunk a wildcard, so a Humble (``TypeHashNotSupported``) and a
    Jazzy publisher are both heard; the bridge then checks the hash itself and counts a mismatch.
    """
    name = f"*/{check_topic(topic)}" if namespace is None else qualified_topic(namespace, topic).strip("/")
    if style == "ros2dds":
        return name
    return f"{domain}/{name}/{dds_type}/*"


@dataclass(frozen=True)
class DataKey:
    """A parsed data key: the publisher's namespace and, in rmw_zenoh style, its type and hash."""

    namespace: str
    dds_type: str | None = None
    type_hash: str | None = None


def parse_data_key(style: Style, domain: int, key: str, topic: str) -> DataKey:
    """Split a received key whose topic ends in ``topic``; ValueError if it is not of that shape."""
    chunks = key.split("/")
    dds_type = type_hash = None
    if style == "rmw_zenoh":
        if len(chunks) < 4 or chunks[0] != str(domain):
            raise ValueError(f"key {key!r} is not <domain {domain}>/<topic>/<type>/<hash>")
        dds_type, type_hash = chunks[-2], chunks[-1]
        chunks = chunks[1:-2]
    topic_chunks = topic.split("/")
    if chunks[-len(topic_chunks) :] != topic_chunks:
        raise ValueError(f"key {key!r} is not topic {topic!r}")
    namespace = normalize_namespace("/".join(chunks[: -len(topic_chunks)]))
    return DataKey(namespace, dds_type, type_hash)


def mangle(name: str) -> str:
    """rmw_zenoh writes ``/`` as ``%`` inside one token chunk (the root namespace ``/`` is ``%``)."""
    return name.replace("/", "%")


def node_token(domain: int, zid: str, node_id: int, namespace: str, node_name: str) -> str:
    """Liveliness key of a node (``NN``), as rmw_zenoh declares it; the enclave is the default ``/``."""
    ns = mangle(normalize_namespace(namespace))
    return f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{node_id}/{NODE}/%/{ns}/{node_name}"


def endpoint_token(
    kind: str,
    domain: int,
    zid: str,
    node_id: int,
    entity_id: int,
    namespace: str,
    node_name: str,
    fq_topic: str,
    dds_type: str,
    type_hash: str,
    qos: str = DEFAULT_QOS,
) -> str:
    """Liveliness key of a publisher (``MP``) or subscription (``MS``): what ``ros2 topic list`` reads."""
    if kind not in (PUBLISHER, SUBSCRIPTION):
        raise ValueError(f"kind must be {PUBLISHER} or {SUBSCRIPTION}, got {kind!r}")
    ns = mangle(normalize_namespace(namespace))
    return (
        f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{entity_id}/{kind}/%/{ns}/{node_name}/"
        f"{mangle(fq_topic)}/{dds_type}/{type_hash}/{qos}"
    )


def check_int64(value: int) -> int:
    if not 0 <= value <= _INT64_MAX:
        raise ValueError(f"{value} does not fit a non-negative int64")
    return value
