"""Data files of the tapecell cell (cell TOML, UR5e model), shipped as package data.

This folder is the package ``tapecell.assets`` (installed or in a checkout). ``asset_path`` finds a file in either case.
"""
from pathlib import Path

ASSETS_DIR = Path(__file__).resolve().parent


def asset_path(name: str) -> Path:
    """Absolute path of a bundled asset file, e.g. ``asset_path("cell.toml")``."""
    return ASSETS_DIR / name
