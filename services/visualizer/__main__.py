"""``python -m services.visualizer``: subscribe to every robot's triscan topics and show them in Rerun.

Wiring only: argparse, the Rerun sink, and :class:`services.runtime.ServiceRuntime` for Zenoh and a
clean shutdown. All drawing lives in ``services.visualizer.core``. The shutdown order matters: the
Zenoh session is closed first (no callback can log any more), then the recording is flushed and
disconnected, which is what writes the ``.rrd`` footer: a recording saved with ``--save`` is complete
after Ctrl-C, SIGTERM or ``--duration`` alike.

The viewer's gRPC URL flag is ``--viewer-url`` because ``--connect`` already names Zenoh endpoints, as
in every triscan service.
"""

from __future__ import annotations

import argparse
import logging
import threading
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal
from urllib.parse import quote

import rerun as rr

from common.keys import DETECTIONS, SCAN, TENSOR, TRACKS, TRUTH, validate_robot_id, wildcard_key
from common.transport import (
    ZenohSettings,
    add_zenoh_arguments,
    settings_from_args,
)
from services.runtime import (
    ServiceRuntime,
    configure_logging,
    exit_code_of,
    exit_process,
    service_parser,
    stop_event_on_signals,
)
from services.visualizer.core import APPLICATION_ID, RerunVisualizer, VisualizerStats

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

SERVICE_NAME = "visualizer"
SUBSCRIBED_TOPICS: tuple[str, ...] = (SCAN, TENSOR, DETECTIONS, TRUTH, TRACKS)
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
FLUSH_TIMEOUT_S = 10.0

SinkKind = Literal["spawn", "connect", "serve_web", "save"]


@dataclass(frozen=True)
class ViewerSink:
    """Where the recording goes: a spawned viewer, a remote one, a served web viewer, or a file."""

    kind: SinkKind
    url: str | None = None  # connect: rerun+http://host:port/proxy
    path: Path | None = None  # save
    grpc_port: int = DEFAULT_GRPC_PORT  # spawn (the viewer's port) and serve_web
    web_port: int = DEFAULT_WEB_PORT  # serve_web
    open_browser: bool = False  # serve_web

    def __post_init__(self) -> None:
        if self.kind == "connect" and not self.url:
            raise ValueError("a 'connect' sink needs a viewer url")
        if self.kind == "save" and self.path is None:
            raise ValueError("a 'save' sink needs a path")


def open_recording(sink: ViewerSink) -> rr.RecordingStream:
    """A new recording stream already attached to ``sink`` (attach before logging anything)."""
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
    if sink.kind == "spawn":
        rec.spawn(port=sink.grpc_port, connect=True)
        log.info("spawned a Rerun viewer on port %d", sink.grpc_port)
    elif sink.kind == "connect":
        assert sink.url is not None
        rec.connect_grpc(sink.url)
        log.info("streaming to the Rerun viewer at %s", sink.url)
    elif sink.kind == "serve_web":
        grpc_url = rec.serve_grpc(grpc_port=sink.grpc_port)
        rr.serve_web_viewer(web_port=sink.web_port, open_browser=sink.open_browser, connect_to=grpc_url)
        log.info(
            "web viewer: http://localhost:%d/?url=%s (native viewer: rerun %s)",
            sink.web_port,
            quote(grpc_url, safe=""),
            grpc_url,
        )
    else:
        assert sink.path is not None
        sink.path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(sink.path)
        log.info("recording to %s", sink.path)
    return rec


def close_recording(rec: rr.RecordingStream) -> None:
    """Flush everything logged and close the sinks (for a file: write its footer)."""
    try:
        rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
    except Exception as exc:  # a viewer that went away must not stop the file sinks from closing
        log.warning("flushing the recording failed: %s", exc)
    rec.disconnect()


def run(
    settings: ZenohSettings,
    sink: ViewerSink,
    stop: threading.Event,
    *,
    robot_ids: Sequence[str] = (),
    duration_s: float | None = None,
) -> VisualizerStats:
    """Visualise every robot's traffic until ``stop`` is set or ``duration_s`` has passed."""
    rec = open_recording(sink)
    try:
        visualizer = RerunVisualizer(rec, robot_ids)

        def counters() -> dict[str, object]:
            snapshot = visualizer.stats()
            return {
                "received": sum(snapshot.accepted.values()) + sum(snapshot.rejected.values()),
                "processed": sum(snapshot.accepted.values()),
                "rejected": snapshot.rejected,
                "robots": len(snapshot.robots),
            }

        with ServiceRuntime(SERVICE_NAME, settings, stop, duration_s=duration_s or 0.0) as runtime:
            for topic in SUBSCRIBED_TOPICS:
                runtime.subscribe(wildcard_key(topic), visualizer.handle)
            log.info("subscribed to %s", ", ".join(wildcard_key(t) for t in SUBSCRIBED_TOPICS))
            runtime.serve(counters)
        stats = visualizer.stats()
        log.info("accepted %s; rejected %s; robots %s", stats.accepted, stats.rejected, list(stats.robots))
        return stats
    finally:
        close_recording(rec)


def _robot_id(text: str) -> str:
    try:
        return validate_robot_id(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = service_parser(
        "services.visualizer",
        "Show every robot's scans, network input, detections and ground truth in Rerun.",
    )
    sinks = parser.add_argument_group("viewer (exactly one)").add_mutually_exclusive_group(required=True)
    sinks.add_argument("--spawn", action="store_true", help="spawn a native Rerun viewer")
    sinks.add_argument(
        "--viewer-url", metavar="URL", help="stream to a running viewer, e.g. rerun+http://host:9876/proxy"
    )
    sinks.add_argument("--serve-web", action="store_true", help="serve the web viewer over HTTP")
    sinks.add_argument("--save", type=Path, metavar="PATH.rrd", help="record headless to an .rrd file")
    parser.add_argument("--grpc-port", type=int, default=DEFAULT_GRPC_PORT, help="--spawn / --serve-web")
    parser.add_argument("--web-port", type=int, default=DEFAULT_WEB_PORT, help="--serve-web HTTP port")
    parser.add_argument("--open-browser", action="store_true", help="--serve-web: open a browser tab")
    parser.add_argument(
        "--robots",
        nargs="+",
        type=_robot_id,
        default=[],
        metavar="ID",
        help="lay out these robots from the start (others are added as they appear)",
    )
    parser.add_argument("--duration", type=_positive_float, default=None, metavar="S", help="stop after S s")
    parser.add_argument("--verbose", "-v", action="store_true")
    add_zenoh_arguments(parser)
    return parser


def sink_from_args(args: argparse.Namespace) -> ViewerSink:
    ports = {"grpc_port": args.grpc_port, "web_port": args.web_port, "open_browser": args.open_browser}
    if args.spawn:
        return ViewerSink("spawn", **ports)
    if args.viewer_url:
        return ViewerSink("connect", url=args.viewer_url, **ports)
    if args.serve_web:
        return ViewerSink("serve_web", **ports)
    return ViewerSink("save", path=args.save, **ports)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    stop = stop_event_on_signals()
    run(
        settings_from_args(args),
        sink_from_args(args),
        stop,
        robot_ids=args.robots,
        duration_s=args.duration,
    )
    return 0


if __name__ == "__main__":
    exit_process(exit_code_of(main))
