"""Where the project's folders are: the one definition (recordings, web pages)."""
from __future__ import annotations

from pathlib import Path

__all__ = ["PROJECT_DIR", "RECORDINGS_DIR", "WEB_DIR"]

PROJECT_DIR = Path(__file__).resolve().parent.parent
RECORDINGS_DIR = PROJECT_DIR / "recordings"
WEB_DIR = PROJECT_DIR / "web"
