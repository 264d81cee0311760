"""Shared fixtures: where the real datasets live, scratch folders, the CLI runner."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

#: ../shared beside the repository (CI puts it there); override with TOPOMAP_SHARED.
SHARED = Path(os.environ.get("TOPOMAP_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))
DATASETS = SHARED / "datasets"


def dataset(name: str) -> Path:
    """Path of a real dataset under ../shared/datasets, skipping the test when it is absent."""
    p = DATASETS / name
    if not p.exists():
        pytest.skip(f"dataset {name} not found under {DATASETS}")
    return p


@pytest.fixture
def runner():
    from typer.testing import CliRunner

    return CliRunner()


@pytest.fixture
def cli_app():
    from topomap_cli.main import app

    return app
