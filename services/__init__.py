"""triscan's processes: simulator, encoder, detector, visualizer, ROS 2 bridge, and the launcher.

Each service is a pure core (tests call it directly) wired to Zenoh by ``services.runtime``.
"""
