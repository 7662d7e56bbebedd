"""Real simulated scans for service tests: a robot driving in a PyBullet room, as wire ``Scan`` messages.

The scans come from the same simulator, LiDAR model and motion code as the data set, so a test that
feeds them to the encoder and detector exercises the shipped model on the kind of input it was
trained for, and can check its detections against the labels of the same scans.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.messages import Scan
from services.simulator.labels import ObjectLabel, label_scan
from services.simulator.lidar import Lidar, LidarSpec
from services.simulator.scenario import sample_scenario
from services.simulator.world import World
from training.dataset import plan_motions, scans_of_motion

REPLAY_SEED = 4242  # not a training seed: scenarios the model has not seen


@dataclass(frozen=True)
class ReplayedScan:
    scan: Scan
    labels: list[ObjectLabel]  # README "Labels" labels of this scan (zero padding)
    motion: int  # which drive it belongs to: the robot jumps between drives


def replay_scans(
    robot_id: str, count: int, *, scenario_index: int = 0, stamp0_ns: int = 1
) -> list[ReplayedScan]:
    """``count`` consecutive scans (seq 0…count−1, 100 ms apart) of one robot's drives in one room."""
    scenario = sample_scenario(scenario_index, REPLAY_SEED)
    spec = LidarSpec()
    out: list[ReplayedScan] = []
    with World(scenario) as world:
        lidar = Lidar(world, spec, rng=np.random.default_rng(scenario_index))
        motions = plan_motions(scenario, REPLAY_SEED, positions=max(1, count // 20 + 1))
        for motion_index, motion in enumerate(motions):
            _, readings = scans_of_motion(lidar, motion)
            for reading in readings:
                seq = len(out)
                if seq == count:
                    return out
                scan = Scan(
                    robot_id=robot_id,
                    seq=seq,
                    stamp_ns=stamp0_ns + seq * 100_000_000,
                    angle_min=spec.angle_min,
                    angle_increment=spec.angle_increment,
                    range_min=spec.range_min,
                    range_max=spec.range_max,
                    ranges=reading.ranges.astype(np.float32),
                )
                labels = label_scan(
                    scenario,
                    reading.lidar_pose,
                    spec.bearings_rad,
                    reading.true_ranges,
                    reading.hit_object,
                    spec.range_max,
                    "zero",
                )
                out.append(ReplayedScan(scan, labels, motion_index))
    raise ValueError(f"scenario {scenario_index} gave only {len(out)} scans, {count} wanted")
