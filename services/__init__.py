"""triscan's processes: simulator-publisher, encoder, detector, visualizer; each thin wiring of a core."""
