"""Offline tooling: data sets, training, export, evaluation.

No robot service imports it. The ``triscan`` subcommands that need it (``dataset``, ``show``,
``train``, ``export``, ``batch-model``, ``eval``, ``card``) import it inside their handlers
(``services/cli/``), so the robot's base install never loads it, torch or Ultralytics.
"""
