"""Where the exported Anny model and anny's build cache live (shared by the loader
``body.anny`` and the exporter ``body.anny_export``; imports nothing of the project)."""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MODEL_PATH = REPO / "assets" / "build" / "anny_model.npz"
DEFAULT_CACHE_DIR = REPO / "assets" / "cache" / "anny"


def model_path() -> Path:
    """Where the exported model lives: ``$ANNY_MODEL_PATH`` or ``assets/build/anny_model.npz``."""
    return Path(os.environ.get("ANNY_MODEL_PATH", str(DEFAULT_MODEL_PATH)))


def cache_dir() -> Path:
    """anny's build cache: ``$ANNY_CACHE_DIR`` or ``assets/cache/anny``."""
    return Path(os.environ.get("ANNY_CACHE_DIR", str(DEFAULT_CACHE_DIR)))
