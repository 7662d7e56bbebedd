"""Offline tooling: data sets, training, export, evaluation.

No robot service imports it. ``services/cli.py`` imports the light ``training.architectures`` for its
flags and the rest lazily inside the subcommands that need it (``dataset``, ``train``, ``export``,
``eval``, ``card``, ``show``), so the robot's base install never loads torch or Ultralytics.
"""
