"""The PyBullet world of SPEC §3: scenarios, world building, the LDS-01 LiDAR, robot motion, labels."""
