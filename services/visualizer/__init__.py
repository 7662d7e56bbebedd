"""Visualizer service: shows scans, network input, detections and ground truth of every robot in Rerun.

``core`` is pure (messages → Rerun log calls on a given recording); ``__main__`` wires it to Zenoh.
"""
