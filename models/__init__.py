"""triscan's shipped models (ONNX files and their cards) as package data.

Installed, this directory is the package ``triscan_models`` (pyproject.toml maps it), not a top-level
``models`` that would collide with other distributions' in site-packages; ``common.model_spec.MODELS_DIR``
finds it either way. It holds no code.
"""
