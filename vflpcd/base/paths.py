"""Where the project's configuration data lives.

``config/`` sits at the top of the source tree (an editable install keeps it there);
``VFLPCD_CONFIG_DIR`` points elsewhere, e.g. ``/etc/vflpcd`` on a vehicle.
"""

from __future__ import annotations

import os
from pathlib import Path


def config_dir() -> Path:
    """The configuration folder: ``$VFLPCD_CONFIG_DIR`` or the source tree's ``config/``."""
    env = os.environ.get("VFLPCD_CONFIG_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "config"
