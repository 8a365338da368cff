"""Builders the test modules share: small generated captures, fake plugins, recordings."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
"""The repository's root folder."""
