"""tether's MJCF models (robots/, scenes/), shipped as package data; this file only locates them."""

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent
