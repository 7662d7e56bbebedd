"""Make Ultralytics run with no network: no downloads, no auto-installs, no telemetry.

Ultralytics reaches for the internet in several places (fonts for plots, pip auto-install of missing
packages, settings sync, pretrained weights). On a robot or an air-gapped CI runner each of those
either hangs or fails late, so every training-side entry point calls :func:`configure_offline`
before importing ``ultralytics``.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
from pathlib import Path

log = logging.getLogger(__name__)

DEFAULT_CONFIG_DIR = Path.home() / ".cache" / "triscan" / "ultralytics"


def _bundled_ttf() -> Path | None:
    """A TrueType font that ships inside an installed package (matplotlib's DejaVu Sans)."""
    try:
        import matplotlib
    except ImportError:
        return None
    font = Path(matplotlib.__file__).parent / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf"
    return font if font.is_file() else None


def configure_offline(config_dir: Path | None = None) -> Path:
    """Set Ultralytics' offline environment; call before the first ``import ultralytics``.

    Plots need ``Arial.ttf`` in the config dir and Ultralytics would download it; a font already on
    disk is copied there instead. Returns the config dir used.
    """
    config_dir = Path(os.environ.get("YOLO_CONFIG_DIR", config_dir or DEFAULT_CONFIG_DIR))
    os.environ["YOLO_CONFIG_DIR"] = str(config_dir)
    os.environ["YOLO_OFFLINE"] = "1"
    os.environ["YOLO_AUTOINSTALL"] = "0"
    font_target = config_dir / "Ultralytics" / "Arial.ttf"
    if not font_target.exists():
        font = _bundled_ttf()
        if font is None:
            log.warning("no bundled TTF found; Ultralytics plots may try to download Arial.ttf")
        else:
            font_target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(font, font_target)
    if "ultralytics" in sys.modules:
        log.debug("ultralytics was imported before configure_offline(); settings may be stale")
    from ultralytics import settings

    settings.update({"sync": False})
    return config_dir
