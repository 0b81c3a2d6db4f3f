"""The engine's state directory: what it keeps on disk between runs (dead letters, de-duplication keys).

``$XDG_STATE_HOME/rabbitros-engine`` (``~/.local/state/rabbitros-engine`` without it), as the XDG
base-directory specification places "data that should persist between restarts but is not
important or portable enough" for the data directory. Read from the environment when asked,
so a test or an operator that sets ``XDG_STATE_HOME`` for one engine gets its own.
"""

from __future__ import annotations

import os
from pathlib import Path


def state_dir() -> Path:
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "rabbitros-engine"
