"""Offline tooling: dataset generation, training, export, evaluation. Never imported by the services."""
