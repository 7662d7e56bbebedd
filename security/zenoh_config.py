"""Zenoh config of one triscan identity in secure mode: mutual TLS plus access control.

Why a generator rather than a checked-in file: every node needs its own key and certificate paths, and
Zenoh's access control matches certificate common names *exactly* (no wildcards), so the rules must name
every robot identity (``triscan-robot-<id>``) of the deployment.

How the rules protect the data keys in a peer-to-peer mesh: Zenoh applies access control on each node to
the messages crossing that node's own transports, and names the remote end by the CN of the certificate
it showed in mutual TLS. Every node therefore carries the *same* rules and checks what comes in
(``ingress``): a ``put`` on ``triscan/<robot>/detections`` is accepted only from a link whose remote CN
is ``triscan-detector``, a scan of robot ``r1`` only from ``triscan-robot-r1`` (or the simulator), a tensor
only from the encoder, truth only from the simulator. A subscriber thus drops a forged publication
at its own door, and a node that forwards data (a peer routing for a client) has already checked it at
its ingress with the original sender's identity. ``egress`` is open for every put the node has, so
it can forward. Anything not allowed (``delete``, queries, other keys, any unknown CN) is denied.

Usage::

    python -m security.zenoh_config --certs certs --identity detector \\
        --listen tls/0.0.0.0:7447 --connect tls/robot.local:7447 > detector.json5
    triscan-service ... --zenoh-config detector.json5
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

from common.keys import (
    DETECTIONS,
    PREFIX,
    SCAN,
    TENSOR,
    TRUTH,
    everything_key,
    scan_key,
    service_keys,
    shard_keys,
    source_keys,
    validate_robot_id,
    wildcard_key,
)

log = logging.getLogger(__name__)

SERVICE_IDENTITIES: Final[tuple[str, ...]] = ("detector", "encoder", "visualizer", "simulator", "app")
"""Identities with one certificate each; ``app`` is a read-only consumer (dashboards, loggers)."""
ROBOT_PREFIX: Final[str] = "robot-"
CN_PREFIX: Final[str] = "triscan-"

# What every member may do on the non-data planes (declarations and health).
_OBSERVE_MESSAGES: Final[list[str]] = [
    "declare_subscriber",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


def common_name(identity: str) -> str:
    """``detector`` → ``triscan-detector``, ``robot-r1`` → ``triscan-robot-r1`` (the certificate CN)."""
    if identity.startswith(ROBOT_PREFIX):
        validate_robot_id(identity[len(ROBOT_PREFIX) :])
    elif identity not in SERVICE_IDENTITIES:
        raise ValueError(f"unknown identity {identity!r}: use one of {SERVICE_IDENTITIES} or robot-<id>")
    return CN_PREFIX + identity


def robots_in(certs_dir: Path) -> list[str]:
    """Robot ids that have a certificate in ``certs_dir`` (``triscan-robot-<id>.pem``)."""
    stem_prefix = CN_PREFIX + ROBOT_PREFIX
    return sorted(p.stem[len(stem_prefix) :] for p in certs_dir.glob(f"{stem_prefix}*.pem"))


def access_control(robots: Sequence[str], *, simulator: bool = True, prefix: str = PREFIX) -> dict[str, Any]:
    """The ``access_control`` section shared by every node of one deployment (see the module docstring)."""
    if not robots:
        raise ValueError("at least one robot id is needed: scans are accepted only from named robots")
    robot_cns = {robot: common_name(ROBOT_PREFIX + validate_robot_id(robot)) for robot in robots}
    members = [common_name(identity) for identity in SERVICE_IDENTITIES] + list(robot_cns.values())
    if not simulator:
        members.remove(common_name("simulator"))
    data = everything_key(prefix)
    health, stats = service_keys(prefix)
    shards = shard_keys(prefix)
    sources = source_keys(prefix)  # which robots' tensors are published: the detectors subscribe by them

    rules: list[dict[str, Any]] = [
        # Declaring interest and watching health: every member, both ways, so subscriptions propagate.
        _rule("observe", _OBSERVE_MESSAGES, ["ingress", "egress"], [data, health, stats, shards, sources]),
        _rule("health-tokens", ["liveliness_token"], ["ingress", "egress"], [health, shards, sources]),
        # A node may send (and forward) every publication it holds; receivers check the source.
        _rule("send", ["put"], ["egress"], [data, stats]),
        _rule("stats-in", ["put"], ["ingress"], [stats]),
        _rule("detections-in", ["put"], ["ingress"], [wildcard_key(DETECTIONS, prefix=prefix)]),
        _rule("tensor-in", ["put"], ["ingress"], [wildcard_key(TENSOR, prefix=prefix)]),
    ]
    subjects: list[dict[str, Any]] = [
        {"id": "members", "cert_common_names": members},
        {"id": "detector", "cert_common_names": [common_name("detector")]},
        {"id": "encoder", "cert_common_names": [common_name("encoder")]},
    ]
    policies: list[dict[str, Any]] = [
        {"id": "members", "rules": ["observe", "health-tokens", "send", "stats-in"], "subjects": ["members"]},
        {"id": "detector", "rules": ["detections-in"], "subjects": ["detector"]},
        {"id": "encoder", "rules": ["tensor-in"], "subjects": ["encoder"]},
    ]
    for robot, cn in robot_cns.items():
        rules.append(_rule(f"scan-{robot}-in", ["put"], ["ingress"], [scan_key(robot, prefix=prefix)]))
        subjects.append({"id": f"robot-{robot}", "cert_common_names": [cn]})
        policies.append(
            {"id": f"robot-{robot}", "rules": [f"scan-{robot}-in"], "subjects": [f"robot-{robot}"]}
        )
    if simulator:
        rules.append(
            _rule(
                "simulator-in",
                ["put"],
                ["ingress"],
                [wildcard_key(SCAN, prefix=prefix), wildcard_key(TRUTH, prefix=prefix)],
            )
        )
        subjects.append({"id": "simulator", "cert_common_names": [common_name("simulator")]})
        policies.append({"id": "simulator", "rules": ["simulator-in"], "subjects": ["simulator"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _rule(rule_id: str, messages: list[str], flows: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": flows,
        "permission": "allow",
        "key_exprs": key_exprs,
    }


def _check_tls(endpoints: Sequence[str], what: str) -> list[str]:
    for endpoint in endpoints:
        if not endpoint.startswith("tls/"):
            raise ValueError(f"{what} endpoint {endpoint!r} is not tls/: secure mode speaks TLS only")
    return list(endpoints)


def secure_config(
    certs_dir: Path,
    identity: str,
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    robots: Sequence[str] | None = None,
    simulator: bool = True,
    mode: str = "peer",
    verify_name_on_connect: bool = True,
    prefix: str = PREFIX,
) -> dict[str, Any]:
    """A complete Zenoh config (as a dict; JSON is valid JSON5) for ``identity``.

    ``robots`` defaults to the robot certificates found in ``certs_dir``. Certificate paths are made
    absolute so the file works from any working directory.
    """
    certs_dir = certs_dir.resolve()
    cn = common_name(identity)
    ca, cert, key = certs_dir / "ca.pem", certs_dir / f"{cn}.pem", certs_dir / f"{cn}.key"
    for path in (ca, cert, key):
        if not path.is_file():
            raise FileNotFoundError(f"{path} not found: run security/make_certs.sh {certs_dir} first")
    robots = list(robots) if robots is not None else robots_in(certs_dir)
    tls = {
        "root_ca_certificate": str(ca),
        "listen_private_key": str(key),
        "listen_certificate": str(cert),
        "connect_private_key": str(key),
        "connect_certificate": str(cert),
        "enable_mtls": True,
        "verify_name_on_connect": verify_name_on_connect,
        "close_link_on_expiration": True,
    }
    return {
        "mode": mode,
        "listen": {"endpoints": _check_tls(listen, "listen")},
        "connect": {"endpoints": _check_tls(connect, "connect")},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"protocols": ["tls"], "tls": tls}},
        "access_control": access_control(robots, simulator=simulator, prefix=prefix),
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m security.zenoh_config", description=__doc__.split("\n")[0], allow_abbrev=False
    )
    parser.add_argument(
        "--certs", type=Path, required=True, help="directory written by security/make_certs.sh"
    )
    parser.add_argument("--identity", required=True, help=f"one of {SERVICE_IDENTITIES} or robot-<id>")
    parser.add_argument(
        "--listen", action="append", default=[], metavar="ENDPOINT", help="e.g. tls/0.0.0.0:7447"
    )
    parser.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="e.g. tls/host:7447"
    )
    parser.add_argument(
        "--robot", action="append", default=None, help="robot id (default: certificates found)"
    )
    parser.add_argument("--no-simulator", action="store_true", help="accept scans only from robot identities")
    parser.add_argument("--mode", choices=("peer", "client", "router"), default="peer")
    parser.add_argument(
        "--no-verify-name",
        action="store_true",
        help="do not check the connected host against the certificate SANs (the CA and CN still are)",
    )
    parser.add_argument("--prefix", default=PREFIX, help="key prefix of the deployment")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        config = secure_config(
            args.certs,
            args.identity,
            listen=args.listen,
            connect=args.connect,
            robots=args.robot,
            simulator=not args.no_simulator,
            mode=args.mode,
            verify_name_on_connect=not args.no_verify_name,
            prefix=args.prefix,
        )
    except (ValueError, FileNotFoundError) as exc:
        log.error("%s", exc)
        return 2
    print(json.dumps(config, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
