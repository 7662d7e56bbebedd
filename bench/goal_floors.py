"""How near the pipeline-overhead goals can come on this host: what Zenoh alone takes, in one run.

The goals leave the pipeline a budget beside its network: at 10 Hz, 1.0 ms of latency for three
processes and 0.5 ms for ``--from-scans`` (:data:`bench.pipeline_latency.OVERHEAD_GOAL_P50_MS`); in a
fleet, 80 % of the network's best throughput (:data:`bench.fleet_bound.FLEET_GOAL_SHARE`). Whatever the
services' own code costs, their messages must cross Zenoh, and this bench prices only that, with nothing
of triscan's on either end, so that its figures are floors no change to the services can go under:

* **latency**: one hop = half a Zenoh round trip between two Python processes at 10 Hz
  (:func:`bench.zenoh_rtt.run_case`, a 100-byte message and the 73 KB tensor; bare TCP beside it).
  Three processes cross three hops (scan, tensor, detections), ``--from-scans`` two; the scan and the
  detections are priced as 100-byte messages, smaller than they are.
* **fleet**: the network's CPU a frame at its best setting (:func:`bench.fleet_bound.compute_bound`),
  plus the CPU each end of a hop spends per message (:func:`bench.zenoh_rtt.cpu_per_message`) at the
  rate the goal asks for (80 % of the bound's frames/s), summed over the ends a scan crosses on this
  host. At that cost per scan, all cores busy, the host serves at most ``cores ÷ cost`` scans a second,
  a share of the bound that no scheduling lifts. Three layouts: the detector alone on its host (the
  robots elsewhere: only its own receive of the tensor and send of the detections), the robots'
  stand-in sharing the host (``bench.fleet_bound --encode-on-robots``), and the three processes of the
  fleet benches (the stand-in's scans through the encoder as well).

    python -m bench.goal_floors --out bench/results/goal_floors.json
"""

from __future__ import annotations

import argparse
import logging
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any, Final

from bench.fleet_bound import FLEET_GOAL_SHARE, compute_bound, network_cpu_ms_per_frame
from bench.machine import machine_info
from bench.pipeline_latency import FROM_SCANS_OVERHEAD_GOAL_P50_MS, OVERHEAD_GOAL_P50_MS
from bench.report import write_report
from bench.zenoh_rtt import (
    DEFAULT_IDLE_S,
    PAYLOADS,
    SMALL_BYTES,
    TENSOR_BYTES,
    cpu_per_message,
    median_p50s,
    run_cases_in_turns,
)
from services.detector.batch_cap import detector_model_and_batch

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "goal_floors.json"

# Which message ends each fleet layout puts on the host, per scan: (message size, end).
FLEET_LAYOUTS: Final[dict[str, tuple[tuple[int, str], ...]]] = {
    "detector alone (robots on other hosts)": ((TENSOR_BYTES, "receiver"), (SMALL_BYTES, "sender")),
    "detector + robots' stand-in sending tensors (--encode-on-robots)": (
        (TENSOR_BYTES, "sender"), (TENSOR_BYTES, "receiver"),
        (SMALL_BYTES, "sender"), (SMALL_BYTES, "receiver"),
    ),
    "stand-in + encoder + detector (the fleet benches)": (
        (SMALL_BYTES, "sender"), (SMALL_BYTES, "receiver"),
        (TENSOR_BYTES, "sender"), (TENSOR_BYTES, "receiver"),
        (SMALL_BYTES, "sender"), (SMALL_BYTES, "receiver"),
    ),
}  # fmt: skip


def hop_ms(summary: list[dict[str, Any]], kind: str, size: int) -> float:
    """Half the median p50 round trip of ``kind`` messages of ``size`` bytes, from the rows of
    :func:`bench.zenoh_rtt.median_p50s`."""
    medians = [row["median_p50_ms"] for row in summary if row["kind"] == kind and row["bytes"] == size]
    if not medians:
        raise ValueError(f"no {kind} round trip of {size} bytes was measured")
    return round(medians[0] / 2, 3)


def latency_floors(round_trips: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each latency goal's budget against the Zenoh hops its pipeline cannot do without."""
    summary = median_p50s(round_trips)
    small, tensor = hop_ms(summary, "zenoh", SMALL_BYTES), hop_ms(summary, "zenoh", TENSOR_BYTES)
    tcp_small, tcp_tensor = hop_ms(summary, "tcp", SMALL_BYTES), hop_ms(summary, "tcp", TENSOR_BYTES)
    goals = (
        ("3 processes", "scan, tensor, detections", OVERHEAD_GOAL_P50_MS,
         2 * small + tensor, 2 * tcp_small + tcp_tensor),
        ("--from-scans", "scan, detections", FROM_SCANS_OVERHEAD_GOAL_P50_MS, 2 * small, 2 * tcp_small),
    )  # fmt: skip
    return [
        {"pipeline": pipeline, "hops": hops, "goal_overhead_p50_ms": goal,
         "zenoh_hops_p50_ms": round(zenoh, 3), "tcp_hops_p50_ms": round(tcp, 3),
         "within_goal": zenoh <= goal}
        for pipeline, hops, goal, zenoh, tcp in goals
    ]  # fmt: skip


def fleet_floors(
    bound: dict[str, Any], message_cpu: list[dict[str, Any]], cores: int, kind: str = "zenoh"
) -> list[dict[str, Any]]:
    """Each layout's least CPU a scan (the network plus the message ends it puts on this host) and
    the share of the bound that cost allows with every core busy."""
    cpu = {
        (m["bytes"], end): ms
        for m in message_cpu
        if m["kind"] == kind
        for end, ms in m["cpu_ms_per_message"].items()
    }
    network_ms = network_cpu_ms_per_frame(bound, cores)
    best = float(bound["best_frames_per_s"])
    rows = []
    for layout, ends in FLEET_LAYOUTS.items():
        messages_ms = sum(cpu[end] for end in ends)
        per_scan = network_ms + messages_ms
        scans_per_s = 1e3 * cores / per_scan
        rows.append(
            {"layout": layout, "network_cpu_ms_per_frame": round(network_ms, 3),
             "message_cpu_ms_per_scan": round(messages_ms, 3), "cpu_ms_per_scan": round(per_scan, 3),
             "most_scans_per_s": round(scans_per_s, 1), "share_of_bound": round(scans_per_s / best, 3),
             "within_goal": scans_per_s / best >= FLEET_GOAL_SHARE}
        )  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3, help="times each round trip case runs, in turns")
    parser.add_argument("--count", type=int, default=60, help="round trips per case")
    parser.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    parser.add_argument("--idle", type=float, default=DEFAULT_IDLE_S, help="seconds of each idle window")
    parser.add_argument("--cpu-seconds", type=float, default=5.0, help="seconds of each message-CPU window")
    parser.add_argument("--bound-seconds", type=float, default=3.0, help="seconds per batch/thread setting")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cores = os.cpu_count() or 1
    model, _ = detector_model_and_batch(None, None)  # the model the detector runs by default
    bound: dict[str, Any] = compute_bound(model, args.bound_seconds)
    goal_rate = FLEET_GOAL_SHARE * float(bound["best_frames_per_s"])  # scans/s at the fleet goal
    log.info(
        "compute bound %.1f frames/s; messages priced at %.0f a second", bound["best_frames_per_s"], goal_rate
    )
    message_cpu = [
        cpu_per_message(kind, size, goal_rate, args.cpu_seconds, args.idle)
        for kind in ("zenoh", "tcp")
        for size in PAYLOADS
    ]
    cases = [("zenoh", "default", size) for size in PAYLOADS] + [("tcp", "-", size) for size in PAYLOADS]
    round_trips = run_cases_in_turns(cases, args.rounds, args.count, args.rate, args.idle)
    report: dict[str, Any] = {
        "latency": latency_floors(round_trips),
        "fleet": fleet_floors(bound, message_cpu, cores),
        "fleet_over_tcp": fleet_floors(bound, message_cpu, cores, kind="tcp"),
        "bound": bound,
        "message_cpu": message_cpu,
        "round_trips": round_trips,
        "machine": asdict(machine_info()),
    }
    write_report(report, args.out, echo=False)
    for row in report["latency"]:
        log.info("%s: Zenoh's hops (%s) alone take %.2f ms at p50 (bare TCP %.2f) against a %.1f ms goal: %s",
                 row["pipeline"], row["hops"], row["zenoh_hops_p50_ms"], row["tcp_hops_p50_ms"],
                 row["goal_overhead_p50_ms"], "within" if row["within_goal"] else "over")  # fmt: skip
    for row in report["fleet"]:
        log.info("%s: at least %.2f ms of CPU a scan (network %.2f + Zenoh %.2f): at most %.0f %% of "
                 "the bound (goal %.0f %%)", row["layout"], row["cpu_ms_per_scan"],
                 row["network_cpu_ms_per_frame"], row["message_cpu_ms_per_scan"],
                 100 * row["share_of_bound"], 100 * FLEET_GOAL_SHARE)  # fmt: skip
    log.info("written to %s", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
