"""The pure core every triscan process shares: encoding, messages, keys (numpy, no simulator, no torch)."""
