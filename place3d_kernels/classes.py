"""Place3D semantic classes (CARLA tags), as used in the paper (Li et al., NeurIPS 2024, Sec. 3)."""

from __future__ import annotations

import numpy as np

__all__ = ["CLASSES", "N_CLASSES", "CLASS_ID", "VEHICLE", "DET_CLASSES", "REFLECTIVITY", "GROUND_CLASSES"]

#: Class names by id; 0 is "unlabeled". "Empty" is not a point class: it is channel 0 of the P-SOG.
CLASSES = (
    "unlabeled", "building", "fence", "other", "pedestrian", "pole", "road line", "road", "sidewalk",
    "vegetation", "vehicle", "wall", "traffic sign", "ground", "bridge", "rail track", "guard rail",
    "traffic light", "static", "dynamic", "water", "terrain",
)
N_CLASSES = len(CLASSES)  # 22 including unlabeled; P-SOG channels: empty + 21 classes = 22
CLASS_ID = {name: i for i, name in enumerate(CLASSES)}
VEHICLE = CLASS_ID["vehicle"]
#: Detection variant of the SOG: empty / vehicle / other occupied.
DET_CLASSES = ("empty", "vehicle", "other")
GROUND_CLASSES = (CLASS_ID["road"], CLASS_ID["road line"], CLASS_ID["sidewalk"], CLASS_ID["ground"],
                  CLASS_ID["terrain"])

#: Diffuse reflectivity per class at 905 nm, used for simulated intensity. Rough, plausible values
#: (asphalt dark, paint and signs bright); they shape intensities, not the metric.
REFLECTIVITY = np.array([
    0.10,  # unlabeled
    0.35,  # building
    0.30,  # fence
    0.25,  # other
    0.30,  # pedestrian
    0.40,  # pole
    0.70,  # road line
    0.12,  # road
    0.25,  # sidewalk
    0.45,  # vegetation
    0.50,  # vehicle
    0.35,  # wall
    0.85,  # traffic sign
    0.20,  # ground
    0.30,  # bridge
    0.25,  # rail track
    0.60,  # guard rail
    0.40,  # traffic light
    0.30,  # static
    0.30,  # dynamic
    0.05,  # water
    0.25,  # terrain
], dtype=np.float64)


def to_detection(labels: np.ndarray) -> np.ndarray:
    """Map Place3D classes to the detection classes: 0 unlabeled, 1 vehicle, 2 any other class."""
    lab = np.asarray(labels)
    out = np.where(lab == VEHICLE, 1, np.where(lab > 0, 2, 0))
    return out.astype(np.int32)
