"""Where the repository is, for tests in any folder under tests/."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
"""The repository's root (this file is tests/support/repo.py)."""
