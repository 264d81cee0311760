"""Re-create the wall photographs of this folder from the real images in ../shared/datasets.

Run from the repository root: ``python datasets/textures/make_textures.py [SHARED_DATASETS_DIR]``.
Each crop is contrast-stretched (1st-99th percentile per channel, the originals were taken at dusk)
and resized to 288 px height; the crop boxes are listed in PROVENANCE.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
HEIGHT_PX = 288

#: name -> (dataset-relative image, x, y, w, h) on the original image [px]
CROPS = {
    "castle_facade_a": ("castle-p30/images/0008.jpg", 0, 110, 300, 320),
    "castle_facade_b": ("castle-p30/images/0008.jpg", 440, 110, 260, 320),
    "castle_windows_tree": ("castle-p30/images/0002.jpg", 300, 170, 270, 260),
    "castle_balcony": ("castle-p30/images/0014.jpg", 520, 90, 248, 350),
    "castle_tower_brick": ("castle-p30/images/0014.jpg", 160, 200, 190, 250),
    "castle_windows_arch": ("castle-p30/images/0022.jpg", 0, 100, 300, 340),
    "castle_door_arch": ("castle-p30/images/0027.jpg", 500, 120, 268, 330),
    "castle_arcade": ("castle-p30/images/0027.jpg", 0, 150, 240, 290),
    "castle_ornate_windows": ("castle-p30/images/0005.jpg", 0, 70, 260, 330),
    "castle_tree_arch": ("castle-p30/images/0005.jpg", 500, 110, 268, 290),
    "castle_gate": ("castle-p30/images/0018.jpg", 400, 180, 170, 230),
    "castle_wing": ("castle-p30/images/0018.jpg", 0, 100, 260, 320),
}


def stretch(img: np.ndarray) -> np.ndarray:
    lo = np.percentile(img, 1, axis=(0, 1))
    hi = np.percentile(img, 99, axis=(0, 1))
    out = (img.astype(np.float64) - lo) * (255.0 / np.maximum(hi - lo, 1.0))
    return np.clip(out, 0, 255).astype(np.uint8)


def main(shared: Path) -> None:
    for name, (rel, x, y, w, h) in CROPS.items():
        img = cv2.imread(str(shared / rel), cv2.IMREAD_COLOR)
        if img is None:
            raise SystemExit(f"cannot read {shared / rel}")
        crop = stretch(img[y : y + h, x : x + w])
        width = round(w * HEIGHT_PX / h)
        crop = cv2.resize(crop, (width, HEIGHT_PX), interpolation=cv2.INTER_AREA if h > HEIGHT_PX else cv2.INTER_CUBIC)
        cv2.imwrite(str(HERE / f"{name}.jpg"), crop, [cv2.IMWRITE_JPEG_QUALITY, 85])
        print(f"{name}.jpg  {width}x{HEIGHT_PX}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parents[2] / "shared" / "datasets")
