"""What the status says of reloads: one engine's (engine/running/runtime.py) and the
supervisor's of ``run --workers N`` (engine/ops/supervisor.py), counted by one rule."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class ReloadStats:
    succeeded: int = 0
    rejected: int = 0
    last_error: list[str] = field(default_factory=list)
    last_reload_s: float = 0.0
    last_handovers: list[dict[str, Any]] = field(default_factory=list)
    """Exclusive resources the last reload handed over break-before-make, with the gap
    (ms from stopping the old routes to the new ones running) during which none was served."""

    def reject(self, problems: list[str]) -> bool:
        """Count a rejected reload once per rejection; False when it is not a new one: the same
        problems found again with nothing applied in between (an editor's save seen as two
        changes, a SIGHUP) are the same rejected files."""
        if problems == self.last_error:
            return False
        self.rejected += 1
        self.last_error = problems
        return True
