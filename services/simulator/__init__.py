"""README "The simulated world": scenarios, the PyBullet world, the LDS-01 LiDAR, robot motion, labels."""
