"""Zenoh sessions for every triscan process: one set of flags, one way to open and close.

Every service takes the same Zenoh flags (``--connect``, ``--listen``, ``--mode``, ``--zenoh-config``,
``--discover``), and falls back to a config file named by ``ZENOH_CONFIG``, as zenoh's own tools do.
``open_session`` is a context manager because a session with a callback subscriber keeps the
interpreter alive at exit unless it is closed explicitly.

A triscan process joins only the network it is pointed at: Zenoh's multicast scouting, which would
connect it to every Zenoh peer that answers on the LAN (another ``triscan up`` on the host, a
colleague's robot), is off unless ``--discover`` asks for it, whatever a config file says. Gossip
scouting stays on: it only tells a peer about the peers of those it is already connected to, so
``triscan status -e <launcher>`` reaches the launcher's children, and nothing beyond.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

ZENOH_CONFIG_ENV = "ZENOH_CONFIG"
LOW_LATENCY_KEY = "transport/unicast/lowlatency"  # measured unsafe for triscan's messages: warned about
MULTICAST_KEY = "scouting/multicast/enabled"
MODES = ("peer", "client", "router")
# <protocol>/<address>: zenoh's own check reports a missing protocol as a JSON5 error with a Rust path.
_ENDPOINT_RE = re.compile(r"[a-z][a-z0-9+-]*/[^/\s].*")
_RUST_LOCATION_RE = re.compile(r" at /\S+?\.rs:\d+\.?")


class ZenohSetupError(ValueError):
    """A Zenoh session that cannot be opened as asked (bad endpoint or entry, port in use); the text
    says what to change, in one line."""


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it reads ``<protocol>/<address>`` (``tcp/10.0.0.2:7447``), else ZenohSetupError."""
    if not _ENDPOINT_RE.fullmatch(endpoint):
        hint = f": write tcp/{endpoint}" if "/" not in endpoint else ""
        raise ZenohSetupError(f"zenoh endpoint {endpoint!r} has no <protocol>/ in front{hint}")
    return endpoint


def zenoh_error_text(exc: BaseException) -> str:
    """A zenoh error's message without the Rust source locations it carries."""
    return " ".join(_RUST_LOCATION_RE.sub("", str(exc)).split())


@dataclass(frozen=True)
class ZenohSettings:
    """What a process needs to join the triscan Zenoh network.

    ``config_file`` is read first (JSON5, zenoh's own format); the explicit fields override it.
    ``multicast_scouting`` (``--discover``) is off by default: peers come from ``connect`` and
    ``listen`` (and the config file's endpoints) alone.
    """

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    config_file: Path | None = None
    extra_json5: dict[str, Any] = field(default_factory=dict)  # config path (a/b/c) → value, e.g. for TLS
    # zenoh's own ``--cfg KEY:VALUE``: a config path and a JSON5 value, applied last, as given.
    cfg: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {MODES}, got {self.mode!r}")
        for endpoint in (*self.connect, *self.listen):
            check_endpoint(endpoint)

    @classmethod
    def loopback(cls, listen_port: int | None, connect_ports: Sequence[int] = ()) -> ZenohSettings:
        """A peer on 127.0.0.1 with explicit endpoints and no multicast: tests and ``triscan up``."""
        return cls(
            mode="peer",
            listen=(f"tcp/127.0.0.1:{listen_port}",) if listen_port is not None else (),
            connect=tuple(f"tcp/127.0.0.1:{port}" for port in connect_ports),
            multicast_scouting=False,
        )

    def to_cli(self) -> list[str]:
        """The flags that reproduce these settings in a child process."""
        args: list[str] = []
        if self.config_file is not None:
            args += ["--zenoh-config", str(self.config_file)]
        if self.mode is not None:
            args += ["--mode", self.mode]
        for endpoint in self.connect:
            args += ["--connect", endpoint]
        for endpoint in self.listen:
            args += ["--listen", endpoint]
        args.append("--discover" if self.multicast_scouting else "--no-multicast")
        for key, value in self.cfg:
            args += ["--cfg", f"{key}:{value}"]
        return args

    def to_config(self) -> Any:
        """A ``zenoh.Config``: file (or ``$ZENOH_CONFIG``) first, then the explicit settings."""
        import zenoh

        config_file = self.config_file
        if config_file is None and os.environ.get(ZENOH_CONFIG_ENV):
            config_file = Path(os.environ[ZENOH_CONFIG_ENV])
        if config_file is not None:
            if not config_file.is_file():
                raise FileNotFoundError(f"zenoh config file {config_file} not found")
            try:
                config = zenoh.Config.from_file(str(config_file))
            except zenoh.ZError as exc:
                raise ZenohSetupError(f"zenoh config file {config_file}: {zenoh_error_text(exc)}") from exc
        else:
            config = zenoh.Config()
        if self.mode is not None:
            config.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        config.insert_json5(MULTICAST_KEY, json.dumps(self.multicast_scouting))
        for key, value in self.extra_json5.items():
            config.insert_json5(key, json.dumps(value))
        for key, value in self.cfg:
            try:
                config.insert_json5(key, value)
            except Exception as exc:  # zenoh raises its own error type for a bad path or value
                raise ZenohSetupError(f"--cfg {key}:{value}: {zenoh_error_text(exc)}") from exc
        if config.get_json(LOW_LATENCY_KEY) == "true":
            log.warning(
                "%s is on: that transport does not fragment and drops messages larger than its batch "
                "without an error, among them the 73 KB tensors (bench/README.md, 'Pipeline latency')",
                LOW_LATENCY_KEY,
            )
        return config


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags every triscan service accepts."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", choices=MODES, default=None, help="zenoh session mode (default: peer)")
    group.add_argument(
        "--connect",
        "-e",
        action="append",
        default=[],
        type=_endpoint_argument,
        metavar="ENDPOINT",
        help="e.g. tcp/192.168.1.10:7447",
    )
    group.add_argument(
        "--listen",
        "-l",
        action="append",
        default=[],
        type=_endpoint_argument,
        metavar="ENDPOINT",
        help="e.g. tcp/0.0.0.0:7447",
    )
    scouting = group.add_mutually_exclusive_group()
    scouting.add_argument(
        "--discover",
        action="store_true",
        help="also find Zenoh peers by multicast scouting (default: only --connect, --listen, config file)",
    )
    scouting.add_argument(
        "--no-multicast", action="store_true", help="no multicast scouting (the default; kept for scripts)"
    )
    group.add_argument(
        "--zenoh-config",
        "-c",
        "--config",
        dest="zenoh_config",
        type=Path,
        default=None,
        metavar="FILE",
        help=f"zenoh JSON5 config file (default: ${ZENOH_CONFIG_ENV} if set)",
    )
    group.add_argument(
        "--cfg",
        action="append",
        default=[],
        type=parse_cfg_entry,
        metavar="KEY:VALUE",
        help="one zenoh config entry as zenoh's tools take it, e.g. 'scouting/multicast/enabled:false'",
    )


def _endpoint_argument(text: str) -> str:
    try:
        return check_endpoint(text)
    except ZenohSetupError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parse_cfg_entry(text: str) -> tuple[str, str]:
    """``KEY:VALUE`` of zenoh's ``--cfg`` flag: a config path and a JSON5 value."""
    key, sep, value = text.partition(":")
    if not sep or not key or not value:
        raise argparse.ArgumentTypeError(f'--cfg takes KEY:VALUE (e.g. mode:"client"), got {text!r}')
    return key, value


def settings_from_args(args: argparse.Namespace) -> ZenohSettings:
    return ZenohSettings(
        mode=args.mode,
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        multicast_scouting=args.discover,
        config_file=args.zenoh_config,
        cfg=tuple(args.cfg),
    )


@contextmanager
def open_session(settings: ZenohSettings) -> Iterator[Any]:
    """An open ``zenoh.Session`` that is always closed on the way out (even on an exception).

    A session zenoh refuses to open (a port in use, say) raises ZenohSetupError with what to do.
    """
    import zenoh

    config = settings.to_config()
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohSetupError(_open_advice(settings, zenoh_error_text(exc))) from exc
    try:
        yield session
    finally:
        session.close()


def _open_advice(settings: ZenohSettings, error: str) -> str:
    if "Address already in use" in error:
        return (
            f"cannot open the zenoh session: {error}: another process (another triscan up?) listens "
            "there: stop it or pick another --listen"
        )
    return f"cannot open the zenoh session ({settings.mode or 'peer'} mode): {error}"


def payload_bytes(sample: Any) -> bytes:
    """The bytes of a received ``zenoh.Sample``."""
    return sample.payload.to_bytes()


def wait_for_subscriber(session: Any, key: str, timeout_s: float = 30.0) -> None:
    """Block until some remote subscriber matches ``key``, so nothing published next is lost.

    Zenoh drops a put nobody subscribes to; a replayer or benchmark that starts publishing before its
    peers have connected loses its first messages. Raises ``TimeoutError`` after ``timeout_s``.
    """
    publisher = session.declare_publisher(key)
    try:
        deadline = time.monotonic() + timeout_s
        while not publisher.matching_status.matching:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no subscriber matched {key} within {timeout_s:.0f} s")
            time.sleep(0.02)
    finally:
        publisher.undeclare()
