"""SemanticKITTI class tables (``semantic-kitti.yaml``; data_metrics.md §1.6-1.7)."""

from __future__ import annotations

import numpy as np

RAW_NAMES: dict[int, str] = {
    0: "unlabeled", 1: "outlier", 10: "car", 11: "bicycle", 13: "bus", 15: "motorcycle", 16: "on-rails",
    18: "truck", 20: "other-vehicle", 30: "person", 31: "bicyclist", 32: "motorcyclist", 40: "road",
    44: "parking", 48: "sidewalk", 49: "other-ground", 50: "building", 51: "fence", 52: "other-structure",
    60: "lane-marking", 70: "vegetation", 71: "trunk", 72: "terrain", 80: "pole", 81: "traffic-sign",
    99: "other-object", 252: "moving-car", 253: "moving-bicyclist", 254: "moving-person",
    255: "moving-motorcyclist", 256: "moving-on-rails", 257: "moving-bus", 258: "moving-truck",
    259: "moving-other-vehicle",
}
RAW_IDS = {name: rid for rid, name in RAW_NAMES.items()}

LEARNING_MAP: dict[int, int] = {
    0: 0, 1: 0, 10: 1, 11: 2, 13: 5, 15: 3, 16: 5, 18: 4, 20: 5, 30: 6, 31: 7, 32: 8, 40: 9, 44: 10,
    48: 11, 49: 12, 50: 13, 51: 14, 52: 0, 60: 9, 70: 15, 71: 16, 72: 17, 80: 18, 81: 19, 99: 0,
    252: 1, 253: 7, 254: 6, 255: 8, 256: 5, 257: 5, 258: 4, 259: 5,
}
LEARNING_MAP_INV: dict[int, int] = {
    0: 0, 1: 10, 2: 11, 3: 15, 4: 18, 5: 20, 6: 30, 7: 31, 8: 32, 9: 40, 10: 44, 11: 48, 12: 49,
    13: 50, 14: 51, 15: 70, 16: 71, 17: 72, 18: 80, 19: 81,
}
CLASS_NAMES: list[str] = [
    "empty", "car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist",
    "motorcyclist", "road", "parking", "sidewalk", "other-ground", "building", "fence", "vegetation",
    "trunk", "terrain", "pole", "traffic-sign",
]
# RGB, from semantic-kitti.yaml's color_map (which is BGR) at each train id's raw id (learning_map_inv)
CLASS_COLOURS: list[tuple[int, int, int]] = [
    (0, 0, 0), (100, 150, 245), (100, 230, 245), (30, 60, 150), (80, 30, 180), (0, 0, 255), (255, 30, 30),
    (255, 40, 200), (150, 30, 90), (255, 0, 255), (255, 150, 255), (75, 0, 75), (175, 0, 75), (255, 200, 0),
    (255, 120, 50), (0, 175, 0), (135, 60, 0), (150, 240, 80), (255, 240, 150), (255, 0, 0),
]
NUM_CLASSES = 20
IGNORE_INDEX = 255
SCRIBBLE_UNLABELLED = 254  # ScribbleSC: occupied, but no scribble label (distinct from empty = 0)


# SemanticPOSS (JS3C-Net's SSC setup, data_metrics.md §6): 11 semantic classes + empty on the same 256x256x32 grid
POSS_CLASS_NAMES: list[str] = ["empty", "people", "rider", "car", "trunk", "plants", "traffic-sign", "pole",
                               "building", "fence", "bike", "ground"]
POSS_LEARNING_MAP: dict[int, int] = {0: 0, 4: 1, 5: 1, 6: 2, 7: 3, 8: 4, 9: 5, 10: 6, 11: 6, 12: 6, 13: 7, 14: 0, 15: 8,
                                     16: 0, 17: 9, 21: 10, 22: 11}
POSS_LEARNING_MAP_INV: dict[int, int] = {0: 0, 1: 4, 2: 6, 3: 7, 4: 8, 5: 9, 6: 10, 7: 13, 8: 15, 9: 17, 10: 21, 11: 22}
POSS_CLASS_COLOURS: list[tuple[int, int, int]] = [
    (0, 0, 0), (255, 30, 30), (255, 40, 200), (100, 150, 245), (135, 60, 0), (0, 175, 0), (255, 0, 0),
    (255, 240, 150), (255, 200, 0), (255, 120, 50), (100, 230, 245), (255, 0, 255)]


def ssc_lut(learning_map: dict[int, int] | None = None) -> np.ndarray:
    """Raw id -> SSC train id; everything that maps to 0 except raw 0 becomes 255 (§1.7). ``learning_map``: another
    data set's (default SemanticKITTI's)."""
    lut = seg_lut(learning_map)
    lut[lut == 0] = IGNORE_INDEX
    lut[0] = 0
    return lut


def seg_lut(learning_map: dict[int, int] | None = None) -> np.ndarray:
    """Raw id -> segmentation train id (0 = unlabelled / ignored for point segmentation)."""
    table = LEARNING_MAP if learning_map is None else learning_map
    lut = np.zeros(max(max(table) + 1, 360), dtype=np.int32)
    lut[list(table)] = list(table.values())
    return lut


def remap(raw: np.ndarray, lut: np.ndarray, what: str = "labels", ids: str = "SemanticKITTI") -> np.ndarray:
    """Raw ids -> train ids through ``lut``; ``what`` (the file) and ``ids`` (whose raw ids they are: SemanticKITTI,
    SemanticPOSS, SSCBench-KITTI-360) name an id outside the table in the error."""
    raw = np.asarray(raw).astype(np.int64)
    if raw.size and (raw.min() < 0 or raw.max() >= lut.size):
        from distilkit.errors import DataError

        bad = int(raw.min()) if raw.min() < 0 else int(raw.max())
        raise DataError(f"{what}: raw id {bad} is not a {ids} label id (they lie in [0, {lut.size}))")
    return lut[raw]
