"""The HTTP app over a daemon built as `clothd run` builds it, in this process (local_cell.py):
never started unless a test starts it."""

from __future__ import annotations

from fastapi import FastAPI
from local_cell import LocalCell

from clothd.api.app import create_app
from clothd.config import ApiConfig
from clothd.run import Parts


def local_app(parts: Parts, api: ApiConfig | None = None, sim_truth_url: str | None = None) -> FastAPI:
    return create_app(
        LocalCell(parts.daemon), parts.hub, parts.camera_model, api or ApiConfig(), sim_truth_url
    )
