"""Tests for common.keys: key builders, wildcards, parsing and robot-id validation."""

from __future__ import annotations

import pytest

from common import keys
from common.keys import (
    ALL_DETECTIONS,
    ALL_SCANS,
    ALL_TENSORS,
    ALL_TRACKS,
    ALL_TRUTH,
    PREFIX,
    ROBOT_ID_MAX_LEN,
    TOPICS,
    detections_key,
    parse_key,
    scan_key,
    tensor_key,
    tracks_key,
    truth_key,
    validate_robot_id,
    wildcard_key,
)


def test_builders_follow_spec_layout() -> None:
    assert PREFIX == "triscan"
    assert scan_key("tb3_0") == "triscan/tb3_0/scan"
    assert tensor_key("tb3_0") == "triscan/tb3_0/tensor"
    assert detections_key("tb3_0") == "triscan/tb3_0/detections"
    assert truth_key("tb3_0") == "triscan/tb3_0/truth"
    assert tracks_key("tb3_0") == "triscan/tb3_0/tracks"


def test_wildcards() -> None:
    assert ALL_SCANS == "triscan/*/scan"
    assert ALL_TENSORS == "triscan/*/tensor"
    assert ALL_DETECTIONS == "triscan/*/detections"
    assert ALL_TRUTH == "triscan/*/truth"
    assert ALL_TRACKS == "triscan/*/tracks"
    assert wildcard_key("scan", prefix="lab/triscan") == "lab/triscan/*/scan"
    with pytest.raises(ValueError, match="unknown topic"):
        wildcard_key("lidar")


def test_builders_accept_prefix() -> None:
    assert scan_key("r1", prefix="site-a") == "site-a/r1/scan"
    assert detections_key("r1", prefix="site-a/triscan") == "site-a/triscan/r1/detections"


@pytest.mark.parametrize("prefix", ["", "a/*", "a//b", "a/", "x$y", "**"])
def test_builders_reject_bad_prefix(prefix: str) -> None:
    with pytest.raises(ValueError, match="prefix"):
        scan_key("r1", prefix=prefix)


@pytest.mark.parametrize(
    "robot_id", ["a/b", "", "*", "**", "a b", "a$", "tb3\n", "é", "x" * (ROBOT_ID_MAX_LEN + 1)]
)
def test_builders_reject_bad_robot_id(robot_id: str) -> None:
    with pytest.raises(ValueError, match="robot_id"):
        scan_key(robot_id)


@pytest.mark.parametrize("robot_id", ["a", "tb3_0", "Robot-7", "0", "x" * ROBOT_ID_MAX_LEN])
def test_validate_robot_id_accepts(robot_id: str) -> None:
    assert validate_robot_id(robot_id) == robot_id


@pytest.mark.parametrize("robot_id", ["a/b", "", "*", "a?", "a#", "tb3\n"])
def test_validate_robot_id_rejects(robot_id: str) -> None:
    with pytest.raises(ValueError, match="one key chunk"):
        validate_robot_id(robot_id)


def test_validate_robot_id_length_message() -> None:
    with pytest.raises(ValueError, match=f"limit is {ROBOT_ID_MAX_LEN}"):
        validate_robot_id("r" * (ROBOT_ID_MAX_LEN + 1))


def test_validate_robot_id_type() -> None:
    with pytest.raises(TypeError):
        validate_robot_id(7)  # type: ignore[arg-type]


@pytest.mark.parametrize("topic", TOPICS)
def test_parse_key_inverts_builders(topic: str) -> None:
    builder = {
        "scan": scan_key,
        "tensor": tensor_key,
        "detections": detections_key,
        "truth": truth_key,
        "tracks": tracks_key,
    }[topic]
    assert parse_key(builder("tb3-1")) == ("tb3-1", topic)
    assert parse_key(builder("r", prefix="lab/triscan"), prefix="lab/triscan") == ("r", topic)


@pytest.mark.parametrize(
    ("key", "fragment"),
    [
        ("triscan/tb3/lidar", "unknown topic"),
        ("triscan/tb3", "form"),
        ("triscan/tb3/scan/extra", "form"),
        ("triscan//scan", "one key chunk"),
        ("triscan/*/scan", "one key chunk"),
        ("other/tb3/scan", "does not start"),
        ("triscanx/tb3/scan", "does not start"),
        ("", "does not start"),
        ("triscan/tb3/scan/", "form"),
    ],
)
def test_parse_key_rejects(key: str, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        parse_key(key)


def test_parse_key_respects_prefix() -> None:
    with pytest.raises(ValueError, match="does not start"):
        parse_key("triscan/r/scan", prefix="lab")
    assert parse_key("lab/r/truth", prefix="lab") == ("r", "truth")


def test_topics_are_the_spec_topics() -> None:
    assert set(keys.TOPICS) == {"scan", "tensor", "detections", "truth", "tracks"}


def test_source_keys_round_trip_and_are_matched_by_their_topic_pattern() -> None:
    key = keys.source_key("tensor", "tb3-1", "a1f3")
    assert key == "triscan/@sources/tensor/tb3-1/a1f3"
    assert keys.parse_source_key(key) == ("tensor", "tb3-1", "a1f3")
    assert keys.topic_sources_key("tensor") == "triscan/@sources/tensor/*/*"
    assert keys.source_keys("lab/triscan") == "lab/triscan/@sources/**"


@pytest.mark.parametrize(
    "key",
    [
        "triscan/@sources/tensor/tb3",  # no source
        "triscan/@sources/tensor/tb3/a1f3/extra",
        "triscan/@sources/lidar/tb3/a1f3",  # unknown topic
        "triscan/@sources/tensor/*/a1f3",  # a pattern, not a robot
        "triscan/@sources/tensor/tb3/",
        "triscan/@shards/detector/a1f3",
        "triscan/tb3/tensor",
    ],
)
def test_parse_source_key_rejects(key: str) -> None:
    with pytest.raises(ValueError, match="source key"):
        keys.parse_source_key(key)


@pytest.mark.parametrize("robot_id", ["", "a/b", "*", "a b"])
def test_source_key_refuses_what_is_not_one_chunk(robot_id: str) -> None:
    with pytest.raises(ValueError):
        keys.source_key("tensor", robot_id, "a1f3")
    with pytest.raises(ValueError):
        keys.source_key("tensor", "tb3", robot_id)
    with pytest.raises(ValueError, match="unknown topic"):
        keys.topic_sources_key("lidar")
