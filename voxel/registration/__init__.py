"""Registration of two maps' geometry: global yaw search, ICP refinement, confidence and verdict."""

from voxel.registration.aligner import Alignment, AlignParams, align_clouds, align_maps
from voxel.registration.landmarks import Landmarks, match_landmarks
from voxel.registration.mapcloud import MapCloud, load_map

__all__ = [
    "AlignParams",
    "Alignment",
    "Landmarks",
    "MapCloud",
    "align_clouds",
    "align_maps",
    "load_map",
    "match_landmarks",
]
