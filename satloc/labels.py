"""Semantic classes shared by the simulator's label images, the satellite label maps and the features."""
from __future__ import annotations

import numpy as np

CLASSES: tuple[str, ...] = (
    "void",          # sky / nothing rendered / unknown
    "road",
    "lane_marking",
    "sidewalk",
    "grass",
    "soil",
    "parking",
    "building",
    "tree",
    "car",
    "person",
    "obstacle",
)
CLASS_ID = {name: i for i, name in enumerate(CLASSES)}
NUM_CLASSES = len(CLASSES)

#: Display colours (RGB) for label images.
PALETTE = np.array(
    [
        (0, 0, 0), (128, 64, 128), (255, 255, 255), (244, 35, 232), (107, 200, 35), (152, 120, 70),
        (180, 180, 200), (70, 70, 70), (30, 120, 30), (0, 0, 142), (220, 20, 60), (250, 170, 30),
    ],
    dtype=np.uint8,
)

#: Classes a vehicle may drive on.
DRIVABLE = (CLASS_ID["road"], CLASS_ID["lane_marking"], CLASS_ID["parking"])


def colorize(labels: np.ndarray) -> np.ndarray:
    """RGB picture of a label image."""
    return PALETTE[np.clip(labels, 0, NUM_CLASSES - 1)]
