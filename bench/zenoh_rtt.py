"""What one Zenoh hop costs between two processes on this host, against a bare TCP socket.

A ping process and an echo process (this module again, ``--echo``) bounce a payload at ``--rate`` Hz,
as the pipeline's messages travel: a 100-byte one and the 73 KB tensor, with Zenoh's defaults, with
express publishers (no batching), with QoS off (one priority queue instead of eight; negotiated per
link, so a peer that keeps it on still connects), with the low-latency transport and with direct
callbacks (run on Zenoh's receiving thread instead of being handed to a Python thread), over a Unix
stream socket instead of TCP, with the transmission queue's batching off (``nobatch``) and with two
transmission threads (``tx2``), then a plain
TCP ping-pong between the same two kinds of process. Round trip = two hops. Peers on loopback,
multicast off. Each case also counts, per round trip, how often each kind of thread in either process
slept and was woken (``wakeups_per_round_trip``, from /proc): the hand-offs a message costs.

:func:`cpu_per_message` prices the other half of a hop, the CPU it takes from each end at a fleet's
rate: one process puts messages at a steady rate without waiting, a counting sink process takes them,
and each end's CPU over the window, less its idle rate, is divided by the messages that arrived.

    python -m bench.zenoh_rtt --rounds 3          # → bench/results/zenoh_rtt.json
    python -m bench.zenoh_rtt --delivery          # → bench/results/zenoh_delivery.json
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from bench.harness import cpu_spinners, proc_cpu_s, thread_wakeups
from bench.machine import machine_info
from bench.report import latency_quantiles_ms, write_report
from common.model_spec import TENSOR_SHAPE
from services.launcher import free_tcp_ports

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

TENSOR_BYTES: Final[int] = math.prod(TENSOR_SHAPE)  # the stacked uint8 tensor: 73,728
SMALL_BYTES: Final[int] = 100  # stands in for a scan or a detections message (both larger)
PAYLOADS: Final[tuple[int, ...]] = (SMALL_BYTES, TENSOR_BYTES)
VARIANTS: Final[tuple[str, ...]] = (
    "default",
    "express",
    "noqos",
    "lowlatency",
    "direct",
    "lowlatency+direct",
    "unix",
    "nobatch",
    "tx2",
)
DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "zenoh_rtt.json"
# --delivery: one put of each size, under each transport, with and without shared memory. The
# low-latency transport does not fragment; the 73 KB tensor is the pipeline's largest message.
DELIVERY_SIZES: Final[tuple[int, ...]] = (1_000, 60_000, TENSOR_BYTES)
DELIVERY_VARIANTS: Final[tuple[str, ...]] = ("default", "noshm", "lowlatency", "lowlatency+noshm")
DELIVERY_OUT: Final[Path] = DEFAULT_OUT.with_name("zenoh_delivery.json")
DEFAULT_IDLE_S: Final[float] = 3.0  # the idle window each case's wake-up count subtracts
WARM_UP_MESSAGES: Final[int] = 20  # sent before each CPU window, not counted
SINK_TALLY_KEY: Final[str] = "rtt/tally"  # a put here asks the sink for its count, answered on ..._ANSWER
SINK_TALLY_ANSWER_KEY: Final[str] = "rtt/tally/answer"


class WakeupCount:
    """Thread wake-ups per round trip in the ping and the echo process, less their idle wake-ups.

    Each process's voluntary context switches per thread name (:func:`bench.harness.thread_wakeups`)
    are read over an idle window with both ends connected and no message (Zenoh's runtime threads wake
    on timers of their own: keep-alives, the shared-memory watchdog) and over the timed loop; the
    loop's count less the idle rate over the loop's duration, divided by the round trips, is how often
    each kind of thread slept and was woken to move one message. The ping side includes its own
    pacing sleep (one a round trip) and its wait for the answer; the echo side is one message in and
    one out.
    """

    def __init__(self, echo_pid: int, idle_s: float = DEFAULT_IDLE_S) -> None:
        self._pids = {"ping": os.getpid(), "echo": echo_pid}
        self.idle_s = idle_s
        self._idle_per_s: dict[str, dict[str, float]] = {}
        self._before: dict[str, dict[str, int]] = {}
        self._started = 0.0
        self.per_round_trip: dict[str, dict[str, float]] = {}

    def _snapshot(self) -> dict[str, dict[str, int]]:
        return {side: thread_wakeups(pid) for side, pid in self._pids.items()}

    @staticmethod
    def _delta(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
        return {name: count - before.get(name, 0) for name, count in after.items()}

    def start(self) -> None:
        """Count the idle window (blocks ``idle_s``), then start counting the loop."""
        self._idle_per_s = {side: {} for side in self._pids}
        if self.idle_s > 0:  # 0: no idle window, timer wake-ups stay in the count
            before, started = self._snapshot(), time.monotonic()
            time.sleep(self.idle_s)
            after, seconds = self._snapshot(), time.monotonic() - started
            self._idle_per_s = {
                side: {name: n / seconds for name, n in self._delta(after[side], before[side]).items()}
                for side in self._pids
            }
        self._before, self._started = self._snapshot(), time.monotonic()

    def stop(self, round_trips: int) -> None:
        after, seconds = self._snapshot(), time.monotonic() - self._started
        for side in self._pids:
            idle = self._idle_per_s[side]
            loop = self._delta(after[side], self._before[side])
            per_trip = {
                name: (n - idle.get(name, 0.0) * seconds) / max(round_trips, 1) for name, n in loop.items()
            }
            self.per_round_trip[side] = {
                name: round(v, 2) for name, v in sorted(per_trip.items()) if round(v, 2) != 0.0
            }


def loopback_endpoint(port: int, unix: bool) -> str:
    """TCP on loopback, or (``unix``) a Unix stream socket named after the same free port."""
    return (
        f"unixsock-stream/{tempfile.gettempdir()}/triscan-rtt-{port}.sock"
        if unix
        else f"tcp/127.0.0.1:{port}"
    )


def zenoh_config(variant: str, listen: int | None, connect: int | None) -> Any:
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    flags = variant.split("+")
    if listen is not None:
        config.insert_json5("listen/endpoints", json.dumps([loopback_endpoint(listen, "unix" in flags)]))
    if connect is not None:
        config.insert_json5("connect/endpoints", json.dumps([loopback_endpoint(connect, "unix" in flags)]))
    if "lowlatency" in flags:
        config.insert_json5("transport/unicast/lowlatency", "true")
    if "lowlatency" in flags or "noqos" in flags:  # the low-latency transport requires QoS off
        config.insert_json5("transport/unicast/qos/enabled", "false")
    if "noshm" in flags:
        config.insert_json5("transport/shared_memory/enabled", "false")
    if "nobatch" in flags:  # the tx queue sends each message alone instead of coalescing under load
        config.insert_json5("transport/link/tx/queue/batching/enabled", "false")
    if "tx2" in flags:  # two transmission threads instead of one
        config.insert_json5("transport/link/tx/threads", "2")
    return config


def subscriber_callback(variant: str, callback: Callable[[Any], Any]) -> Any:
    """The callback as the variant declares it: ``direct`` runs it on Zenoh's receiving thread."""
    import zenoh

    direct = "direct" in variant.split("+")
    return zenoh.handlers.Callback(callback, indirect=False) if direct else callback


def echo(kind: str, variant: str, port: int, stop_after_s: float) -> None:
    """The far end: send back whatever arrives, until ``stop_after_s``; or (``sink``, ``tcp-sink``)
    only count it, answering the count when asked (:func:`cpu_per_message`)."""
    if kind in ("sink", "tcp-sink"):
        count_messages(kind, variant, port, stop_after_s)
        return
    if kind == "tcp":
        server = socket.create_server(("127.0.0.1", port))
        conn, _ = server.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        while data := conn.recv(1 << 17):
            conn.sendall(data)
        return
    import zenoh

    with zenoh.open(zenoh_config(variant, port, None)) as session:
        pub = session.declare_publisher("rtt/pong", express=variant == "express")
        sub = session.declare_subscriber(
            "rtt/ping", subscriber_callback(variant, lambda sample: pub.put(sample.payload))
        )
        time.sleep(stop_after_s)
        sub.undeclare()


def count_messages(kind: str, variant: str, port: int, stop_after_s: float) -> None:
    """The sink of :func:`cpu_per_message`: take every message and count it, nothing else.

    Zenoh's sink answers its count on :data:`SINK_TALLY_ANSWER_KEY` whenever a put arrives on
    :data:`SINK_TALLY_KEY`; the TCP sink reads length-prefixed frames and writes its count back when
    the sender closes its side.
    """
    received = 0
    if kind == "tcp-sink":
        server = socket.create_server(("127.0.0.1", port))
        conn, _ = server.accept()
        stream = conn.makefile("rb")
        while header := stream.read(4):
            stream.read(int.from_bytes(header, "little"))
            received += 1
        conn.sendall(received.to_bytes(8, "little"))
        return
    import zenoh

    def on_message(_sample: Any) -> None:
        nonlocal received
        received += 1

    with zenoh.open(zenoh_config(variant, port, None)) as session:
        answer = session.declare_publisher(SINK_TALLY_ANSWER_KEY)
        sub = session.declare_subscriber("rtt/ping", subscriber_callback(variant, on_message))
        asked = session.declare_subscriber(SINK_TALLY_KEY, lambda _sample: answer.put(str(received)))
        time.sleep(stop_after_s)
        asked.undeclare()
        sub.undeclare()


def _paced(count: int, rate_hz: float, send: Callable[[], None]) -> None:
    """Call ``send`` ``count`` times at a steady ``rate_hz`` (deadlines, not sleeps that drift)."""
    started = time.monotonic()
    for index in range(count):
        if (wait := started + index / rate_hz - time.monotonic()) > 0:
            time.sleep(wait)
        send()


@dataclass
class CpuWindows:
    """The CPU seconds :func:`cpu_per_message` reads: each end while idle with both connected, the
    sender's pacing loop alone (sending nothing), and each end while the messages flow."""

    idle_s: float
    idle_near_s: float
    idle_far_s: float
    pacing_s: float
    pacing_near_s: float
    window_s: float
    near_s: float
    far_s: float
    received: int

    def ms_per_message(self) -> dict[str, float]:
        """Each end's CPU a message: its window less its idle rate, the sender's less its pacing too."""
        idle_near_rate = self.idle_near_s / self.idle_s if self.idle_s > 0 else 0.0
        idle_far_rate = self.idle_far_s / self.idle_s if self.idle_s > 0 else 0.0
        pacing = max(self.pacing_near_s - idle_near_rate * self.pacing_s, 0.0)
        sender = self.near_s - idle_near_rate * self.window_s - pacing
        receiver = self.far_s - idle_far_rate * self.window_s
        return {
            side: round(1e3 * max(cpu, 0.0) / max(self.received, 1), 4)
            for side, cpu in (("sender", sender), ("receiver", receiver), ("sender_pacing", pacing))
        }


def _measure_windows(
    far_pid: int,
    idle_s: float,
    count: int,
    rate_hz: float,
    send: Callable[[], None],
    count_before: Callable[[], int],
    count_after: Callable[[], int],
) -> CpuWindows:
    """Read every window of :class:`CpuWindows`. ``count_before`` and ``count_after`` return the
    sink's count before and after the messages flow, once all sent ones can have arrived (they may
    wait for them)."""
    near, far, started = time.process_time(), proc_cpu_s(far_pid), time.monotonic()
    time.sleep(idle_s)
    idle_near, idle_far, idle = (
        time.process_time() - near,
        proc_cpu_s(far_pid) - far,
        time.monotonic() - started,
    )
    near, started = time.process_time(), time.monotonic()
    _paced(count, rate_hz, lambda: None)
    pacing_near, pacing = time.process_time() - near, time.monotonic() - started
    before = count_before()
    near, far, started = time.process_time(), proc_cpu_s(far_pid), time.monotonic()
    _paced(count, rate_hz, send)
    after = count_after()
    return CpuWindows(
        idle_s=idle, idle_near_s=idle_near, idle_far_s=idle_far, pacing_s=pacing, pacing_near_s=pacing_near,
        window_s=time.monotonic() - started, near_s=time.process_time() - near,
        far_s=proc_cpu_s(far_pid) - far, received=after - before,
    )  # fmt: skip


def cpu_per_message(
    kind: str,
    size: int,
    rate_hz: float,
    seconds: float,
    idle_s: float = DEFAULT_IDLE_S,
    variant: str = "default",
) -> dict[str, Any]:
    """CPU each end of a hop spends per message of ``size`` bytes at ``rate_hz`` messages a second.

    This process puts messages at the rate without waiting for anything (as a fleet's encoder or
    robots do); a sink process (this module, ``--echo sink``) counts them. Each end's CPU over the
    window (every thread: Zenoh's runtime and the Python callback thread included), less the same
    end's CPU over an idle window of ``idle_s`` with both connected (Zenoh's timers), is divided by
    the messages that arrived; the sender's also less what its pacing loop costs sending nothing
    (its sleeps and wake-ups, which a service putting from a callback does not pay). ``kind`` ``tcp``
    prices the same messages over a bare loopback socket with a 4-byte length prefix, the floor any
    transport between two Python processes pays.
    """
    (port,) = free_tcp_ports(1)
    count = max(1, round(rate_hz * seconds))
    far = start_echo("tcp-sink" if kind == "tcp" else "sink", variant, port, 2 * (idle_s + seconds) + 30)
    measure = _tcp_cpu_windows if kind == "tcp" else _zenoh_cpu_windows
    try:
        windows = measure(variant, port, bytes(size), count, rate_hz, idle_s, far.pid)
    finally:
        far.kill()
        far.wait()
    per_message = windows.ms_per_message()
    return {"kind": kind, "variant": variant if kind == "zenoh" else "-", "bytes": size, "rate_hz": rate_hz,
            "sent": count, "received": windows.received, "seconds": round(windows.window_s, 2),
            "cpu_ms_per_message": {side: per_message[side] for side in ("sender", "receiver")},
            "sender_pacing_cpu_ms_per_message": per_message["sender_pacing"],
            "cpu_ms_per_message_both_ends":
                round(per_message["sender"] + per_message["receiver"], 4)}  # fmt: skip


def _zenoh_cpu_windows(
    variant: str, port: int, payload: bytes, count: int, rate_hz: float, idle_s: float, far_pid: int
) -> CpuWindows:
    """The Zenoh side of :func:`cpu_per_message`."""
    import queue

    import zenoh

    tallies: queue.SimpleQueue[int] = queue.SimpleQueue()
    with zenoh.open(zenoh_config(variant, None, port)) as session:
        sub = session.declare_subscriber(
            SINK_TALLY_ANSWER_KEY, lambda sample: tallies.put(int(sample.payload.to_bytes()))
        )
        pub = session.declare_publisher("rtt/ping")
        asker = session.declare_publisher(SINK_TALLY_KEY)

        def ask(timeout_s: float) -> int | None:
            asker.put(b"")
            try:
                return tallies.get(timeout=timeout_s)
            except queue.Empty:
                return None

        def tally() -> int:
            time.sleep(0.2)  # the last messages reach the sink before its count is asked for
            while not tallies.empty():  # late answers to earlier probes
                tallies.get()
            if (count := ask(2.0)) is None:
                raise TimeoutError("the sink did not answer its count")
            return count

        deadline = time.monotonic() + 10.0
        while ask(0.2) is None:  # until the sink answers: peers connect on retry
            if time.monotonic() > deadline:
                raise TimeoutError("the sink never answered")
        _paced(WARM_UP_MESSAGES, rate_hz, lambda: pub.put(payload))
        windows = _measure_windows(far_pid, idle_s, count, rate_hz, lambda: pub.put(payload), tally, tally)
        sub.undeclare()
    return windows


def _tcp_cpu_windows(
    variant: str, port: int, payload: bytes, count: int, rate_hz: float, idle_s: float, far_pid: int
) -> CpuWindows:
    """The TCP side of :func:`cpu_per_message` (``variant`` unused: the same signature as Zenoh's)."""
    del variant
    conn = _connect_tcp(port)
    framed = len(payload).to_bytes(4, "little") + payload
    _paced(WARM_UP_MESSAGES, rate_hz, lambda: conn.sendall(framed))

    def final_count() -> int:
        """The sink answers its count once, when the sender closes its side and it has read all."""
        conn.shutdown(socket.SHUT_WR)
        return int.from_bytes(conn.makefile("rb").read(8), "little")

    windows = _measure_windows(  # before the window the sink holds the warm-up: TCP delivers all of it
        far_pid, idle_s, count, rate_hz, lambda: conn.sendall(framed), lambda: WARM_UP_MESSAGES, final_count
    )
    conn.close()
    return windows


def _connect_tcp(port: int) -> socket.socket:
    """A loopback TCP connection to ``port`` once the far end listens (it starts in parallel)."""
    deadline = time.monotonic() + 10.0
    while True:
        try:
            conn = socket.create_connection(("127.0.0.1", port))
            break
        except ConnectionRefusedError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return conn


def ping_zenoh(
    variant: str, port: int, size: int, count: int, rate_hz: float, wakeups: WakeupCount | None = None
) -> list[float]:
    import zenoh

    got = threading.Event()
    rtts = []
    with zenoh.open(zenoh_config(variant, None, port)) as session:
        sub = session.declare_subscriber("rtt/pong", subscriber_callback(variant, lambda sample: got.set()))
        pub = session.declare_publisher("rtt/ping", express=variant == "express")
        payload = bytes(size)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:  # until the echo answers: peers connect on retry
            got.clear()
            pub.put(payload)
            if got.wait(0.2):
                break
        if wakeups:
            wakeups.start()
        for _ in range(count):
            got.clear()
            started = time.perf_counter_ns()
            pub.put(payload)
            if got.wait(2.0):
                rtts.append((time.perf_counter_ns() - started) / 1e6)
            time.sleep(1.0 / rate_hz)
        if wakeups:
            wakeups.stop(count)
        sub.undeclare()
    return rtts


def ping_tcp(
    port: int, size: int, count: int, rate_hz: float, wakeups: WakeupCount | None = None
) -> list[float]:
    conn = _connect_tcp(port)
    payload, rtts = bytes(size), []
    if wakeups:
        wakeups.start()
    for _ in range(count):
        started = time.perf_counter_ns()
        conn.sendall(payload)
        received = 0
        while received < size:
            received += len(conn.recv(1 << 17))
        rtts.append((time.perf_counter_ns() - started) / 1e6)
        time.sleep(1.0 / rate_hz)
    if wakeups:
        wakeups.stop(count)
    conn.close()
    return rtts


def delivered_zenoh(variant: str, port: int, sizes: tuple[int, ...]) -> list[int]:
    """Put each of ``sizes`` once, 0.3 s apart; the sizes that came back from the echo, in order."""
    import zenoh

    answered = threading.Event()
    back: list[int] = []

    def on_pong(sample: Any) -> None:
        back.append(len(sample.payload.to_bytes()))
        answered.set()

    with zenoh.open(zenoh_config(variant, None, port)) as session:
        sub = session.declare_subscriber("rtt/pong", subscriber_callback(variant, on_pong))
        pub = session.declare_publisher("rtt/ping")
        deadline = time.monotonic() + 10.0
        while not answered.is_set() and time.monotonic() < deadline:  # until the echo is connected
            pub.put(bytes(100))
            answered.wait(0.2)
        time.sleep(0.5)  # late answers to the probes
        back.clear()
        for size in sizes:
            pub.put(bytes(size))
            time.sleep(0.3)
        time.sleep(1.0)
        sub.undeclare()
    return back


def start_echo(kind: str, variant: str, port: int, seconds: float) -> subprocess.Popen[bytes]:
    """This module again as the far end (``--echo``), for ``seconds``."""
    return subprocess.Popen(
        [sys.executable, "-m", "bench.zenoh_rtt", "--echo", kind, variant, str(port), str(seconds)]
    )


def run_delivery(variant: str, sizes: tuple[int, ...] = DELIVERY_SIZES) -> dict[str, Any]:
    (port,) = free_tcp_ports(1)
    far = start_echo("zenoh", variant, port, 30.0)
    try:
        delivered = delivered_zenoh(variant, port, sizes)
    finally:
        far.kill()
        far.wait()
    return {"variant": variant, "sent": list(sizes), "delivered": delivered}


def run_case(
    kind: str, variant: str, size: int, count: int, rate_hz: float, idle_s: float = DEFAULT_IDLE_S
) -> dict[str, Any]:
    (port,) = free_tcp_ports(1)
    far = start_echo(kind, variant, port, idle_s + count / rate_hz + 15)
    wakeups = WakeupCount(far.pid, idle_s)
    try:
        rtts = (
            ping_tcp(port, size, count, rate_hz, wakeups)
            if kind == "tcp"
            else ping_zenoh(variant, port, size, count, rate_hz, wakeups)
        )
    finally:
        far.kill()
        far.wait()
    warm = np.array(rtts[10:])
    return {"kind": kind, "variant": variant, "bytes": size, "answered": len(rtts), "sent": count,
            "rtt_ms": latency_quantiles_ms(warm),
            "wakeups_per_round_trip": wakeups.per_round_trip}  # fmt: skip


def run_cases_in_turns(
    cases: list[tuple[str, str, int]], rounds: int, count: int, rate_hz: float, idle_s: float = DEFAULT_IDLE_S
) -> list[dict[str, Any]]:
    """Every (kind, variant, bytes) case ``rounds`` times, the cases taking turns within a round so
    that a slow minute of the VM hits them all; each result carries its ``round``."""
    results = []
    for round_index in range(rounds):
        for kind, variant, size in cases:
            result = run_case(kind, variant, size, count, rate_hz, idle_s) | {"round": round_index}
            log.info("%-5s %-17s %6d B: answered %d/%d, rtt %s", kind, variant, size, result["answered"],
                     result["sent"], result["rtt_ms"])  # fmt: skip
            results.append(result)
    return results


def median_p50s(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per case: the median over rounds of its p50 round trip and of each side's thread
    wake-ups per round trip (summed over the side's threads)."""
    rounds: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for result in results:
        rounds.setdefault((result["kind"], result["variant"], result["bytes"]), []).append(result)
    rows = []
    for (kind, variant, size), runs in rounds.items():
        wakeups = {
            side: round(float(np.median([sum(r["wakeups_per_round_trip"][side].values()) for r in runs])), 2)
            for side in ("ping", "echo")
        }
        rows.append(
            {"kind": kind, "variant": variant, "bytes": size,
             "median_p50_ms": round(float(np.median([r["rtt_ms"]["p50"] for r in runs])), 3),
             "median_wakeups_per_round_trip": wakeups}
        )  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=100, help="round trips per case")
    parser.add_argument("--rate", type=float, default=10.0, help="round trips per second (the scan rate)")
    parser.add_argument("--rounds", type=int, default=1, help="times every case runs, in turns")
    parser.add_argument(
        "--idle",
        type=float,
        default=DEFAULT_IDLE_S,
        help="seconds of each case's idle window, whose thread wake-ups the per-message count subtracts",
    )
    parser.add_argument(
        "--busy",
        type=int,
        default=0,
        help="lowest-priority processes spinning meanwhile (one per CPU: none idles)",
    )
    parser.add_argument(
        "--variants",
        default=",".join(VARIANTS),
        help=f"Zenoh variants, comma-separated (of {', '.join(VARIANTS)})",
    )
    parser.add_argument(
        "--delivery",
        action="store_true",
        help="instead of timing: which message sizes arrive under each transport, shared memory on and off",
    )
    parser.add_argument("--out", type=Path, default=None, help=f"default {DEFAULT_OUT} ({DELIVERY_OUT})")
    parser.add_argument(
        "--echo", nargs=4, metavar=("KIND", "VARIANT", "PORT", "SECONDS"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.echo:
        kind, variant, port, seconds = args.echo
        echo(kind, variant, int(port), float(seconds))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.delivery:
        checks = [run_delivery(variant) for variant in DELIVERY_VARIANTS]
        for check in checks:
            log.info("%-17s sent %s, delivered %s", check["variant"], check["sent"], check["delivered"])
        write_report({"checks": checks, "machine": asdict(machine_info())}, args.out or DELIVERY_OUT)
        return 0
    variants = args.variants.split(",")
    if unknown := set(variants) - set(VARIANTS):
        parser.error(f"unknown --variants {sorted(unknown)}; choose from {', '.join(VARIANTS)}")
    cases = [("zenoh", variant, size) for variant in variants for size in PAYLOADS]
    cases += [("tcp", "-", size) for size in PAYLOADS]
    with cpu_spinners(args.busy):  # --busy: tell wake-up costs from work per message
        results = run_cases_in_turns(cases, args.rounds, args.count, args.rate, args.idle)
    summary = median_p50s(results)
    for row in summary:
        log.info("median p50 over %d rounds: %-5s %-17s %6d B: %.2f ms, thread wake-ups a round trip %s",
                 args.rounds, row["kind"], row["variant"], row["bytes"], row["median_p50_ms"],
                 row["median_wakeups_per_round_trip"])  # fmt: skip
    report = {
        "rate_hz": args.rate,
        "rounds": args.rounds,
        "busy_spinners": args.busy,
        "summary": summary,
        "results": results,
    }
    write_report(report | {"machine": asdict(machine_info())}, args.out or DEFAULT_OUT)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
