"""Write the fixture map of the *current* schema: ``python tests/data/make_fixture_maps.py``.

Each released schema version keeps one small map in ``tests/data/`` (``corridor-schemaN.topomap``),
written by the topomap that introduced that schema, so that ``tests/test_store_migration.py`` proves
that every old map still opens and localizes. Run this once when a new schema version is released
(with the new code) and commit the new file; never regenerate an old version's file.

The map: sequence 0 = frames 0, 1, 2, 4, 5, 6, 8 of ``datasets/demo/corridor`` (frames 3, 7 and 9 are
held out as queries), sequence 1 (``--append``) = frames 10 and 11; ORB, at most 300 features,
working size 240x180 (``upscale_min_px=240``), 64 visual words, keyframe images stored.
Only the public API is used, so the script runs unchanged on every version.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from topomap.build import build_map
from topomap.config import BuildConfig, FeatureConfig
from topomap.store import SCHEMA_VERSION, load_map, save_map, update_map

HERE = Path(__file__).resolve().parent
DEMO = HERE.parents[1] / "datasets" / "demo" / "corridor"
SEQUENCES = ([0, 1, 2, 4, 5, 6, 8], [10, 11])
CONFIG = BuildConfig(features=FeatureConfig(max_features=300, upscale_min_px=240), vocabulary_words=64)


def main() -> int:
    out = HERE / f"corridor-schema{SCHEMA_VERSION}.topomap"
    if out.exists():
        print(f"{out.name} exists; fixtures of released schema versions are never regenerated", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        folders = []
        for k, frames in enumerate(SEQUENCES):
            folder = Path(tmp) / f"seq{k}"
            folder.mkdir()
            for i in frames:
                shutil.copy(DEMO / f"{i:07d}.jpg", folder)
            folders.append(folder)
        m = build_map(folders[0], CONFIG)
        save_map(m, Path(tmp) / out.name)
        for folder in folders[1:]:
            base = load_map(Path(tmp) / out.name)
            grown = build_map(folder, base=base)
            update_map(grown, Path(tmp) / out.name, first_new_node=len(m.nodes), first_new_frame=len(m.frames))
            m = grown
        shutil.copy(Path(tmp) / out.name, out)
    print(f"wrote {out} ({out.stat().st_size} bytes, {len(m.nodes)} nodes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
