"""Helpers the tests share: waiting on conditions, health tokens, real simulated scans, ROS 2 scans
and wire detections. Fixtures stay in ``tests/conftest.py``; everything else tests import lives here."""
