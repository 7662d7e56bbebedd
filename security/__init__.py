"""Secure mode of triscan: Zenoh mutual TLS plus access control (see ``security/zenoh_config.py``)."""
