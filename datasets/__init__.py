"""Loaders for dataset layouts and the tiny demo data shipped with topomap (installed as ``topomap_datasets``)."""

from __future__ import annotations

from pathlib import Path

#: Folder of the data files shipped inside this package.
DATA_DIR = Path(__file__).resolve().parent
