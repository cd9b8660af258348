"""What the fault tests compare: the bytes of every file under a directory, before and after a fault."""

from __future__ import annotations

import hashlib
from pathlib import Path

from don_gym.io import LOCK_FILE


def snapshot(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` by its path relative to ``root`` (lock files aside: they hold no data)."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(Path(root).rglob("*"))
        if p.is_file() and p.name != LOCK_FILE
    }
