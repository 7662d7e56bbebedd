"""The service skeleton over real Zenoh: the health token means "wired", publishers die with robots."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from common.keys import TENSOR, scan_key, source_key, tensor_key, topic_sources_key
from common.transport import ZenohSettings, open_session
from services.runtime import ANNOUNCE_LEAD_S, RobotPublishers, ServiceRuntime
from tests.support.health import service_pids
from tests.support.waiting import wait_for


def test_the_health_token_appears_only_once_the_service_is_ready(free_port: Callable[[], int]) -> None:
    port = free_port()
    received: list[str] = []
    with (
        ServiceRuntime("probe", ZenohSettings.loopback(port), threading.Event()) as runtime,
        open_session(ZenohSettings.loopback(None, [port])) as watcher,
    ):
        # Prove the two sessions are linked first, or "no token" would prove nothing.
        link = watcher.declare_subscriber("probe/link", lambda sample: None)
        ping = runtime.session.declare_publisher("probe/link")
        assert wait_for(lambda: ping.matching_status.matching, timeout=10)
        assert service_pids(watcher, "probe") == set()  # linked, subscribing to nothing yet: no token
        ping.undeclare()
        link.undeclare()
        runtime.subscribe(scan_key("r1"), lambda key, payload: received.append(key))
        runtime.ready()
        assert wait_for(lambda: service_pids(watcher, "probe"), timeout=10)
        publisher = watcher.declare_publisher(scan_key("r1"))
        assert wait_for(lambda: publisher.matching_status.matching, timeout=10)  # subscribed before ready
        publisher.put(b"x")
        assert wait_for(lambda: received == [scan_key("r1")], timeout=10)
        publisher.undeclare()


def test_robot_publishers_forget_silent_robots(free_port: Callable[[], int]) -> None:
    with open_session(ZenohSettings.loopback(free_port())) as session:
        publishers = RobotPublishers(session, scan_key)
        publishers.put("r1", b"a")
        publishers.put("r2", b"b")
        assert len(publishers) == 2
        later = time.monotonic() + 60
        assert publishers.forget_silent(30.0, now=later) == ["r1", "r2"]
        assert len(publishers) == 0
        publishers.put("r1", b"c")  # a robot that speaks again gets a fresh publisher
        publishers.forget(["r1", "unknown"])
        assert len(publishers) == 0


def test_robot_publishers_announce_each_robot_until_it_is_forgotten(free_port: Callable[[], int]) -> None:
    port = free_port()
    with (
        open_session(ZenohSettings.loopback(port)) as session,
        open_session(ZenohSettings.loopback(None, [port])) as watcher,
    ):

        def sources() -> list[str]:
            replies = watcher.liveliness().get(topic_sources_key(TENSOR), timeout=1.0)
            return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok)

        publishers = RobotPublishers(session, tensor_key, announce_topic=TENSOR)
        publishers.announce("r1")
        started = time.monotonic()
        publishers.put("r1", b"a")  # its first sample waits out the lead the subscriber needs
        assert time.monotonic() - started >= ANNOUNCE_LEAD_S * 0.9
        publishers.put("r2", b"b")
        zid = str(session.zid())
        expected = [source_key(TENSOR, "r1", zid), source_key(TENSOR, "r2", zid)]
        assert wait_for(lambda: sources() == expected, timeout=10)
        publishers.forget(["r1"])
        assert wait_for(lambda: sources() == expected[1:], timeout=10)
        publishers.close()
        assert wait_for(lambda: sources() == [], timeout=10)


def test_a_service_process_ends_with_its_code_and_its_last_log_lines() -> None:
    """``exit_process`` skips Python's finalization (where a Zenoh thread asking for the GIL aborts the
    process) but not what the service wrote last."""
    import subprocess
    import sys

    script = (
        "import logging, sys\n"
        "from services.runtime import exit_process\n"
        "logging.basicConfig(level=logging.INFO)\n"
        "logging.getLogger('svc').info('stopping after 1 s')\n"
        "sys.stdout.write('buffered, not yet flushed')\n"
        "exit_process(3)\n"
        "print('never')\n"
    )
    command = [sys.executable, "-c", script]
    done = subprocess.run(command, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 3
    assert "stopping after 1 s" in done.stderr
    assert done.stdout == "buffered, not yet flushed"
