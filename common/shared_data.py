"""Where the recorded real data (KITTI, Middlebury, F1/10 logs) lives: `../shared/data` next to the
project, or wherever LBC_SHARED_DATA points. Read in place, never copied into the project."""
from __future__ import annotations

import os
from pathlib import Path

ENV = "LBC_SHARED_DATA"


def shared_data_dir() -> Path:
    override = os.environ.get(ENV)
    if override:
        return Path(override)
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"
