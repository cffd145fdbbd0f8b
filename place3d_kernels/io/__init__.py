"""Point-cloud files: SemanticKITTI sequences (read and write, ``io.semantickitti``) and CARLA
semantic-LiDAR PLY (read, ``io.carla``). Every public name is importable from ``place3d_kernels.io``."""

from place3d_kernels.io.carla import CARLA_CITYSCAPES_TO_PLACE3D, CARLA_LEGACY_TO_PLACE3D, CarlaCloud, read_carla_ply
from place3d_kernels.io.semantickitti import (SEMANTICKITTI_TO_PLACE3D, atomic_write, frame_paths, pose_row,
                                              SEQUENCE_META, prepare_sequence_folder,
                                              psog_from_semantickitti, read_poses, read_semantickitti,
                                              read_sequence_metadata, sequence_spec, write_sequence_metadata,
                                              read_sequence, remap_semantickitti, sensor_matrix, write_frame,
                                              write_frame_bin, write_semantickitti_sequence)

__all__ = ["SEMANTICKITTI_TO_PLACE3D", "CARLA_LEGACY_TO_PLACE3D", "CARLA_CITYSCAPES_TO_PLACE3D", "remap_semantickitti",
           "read_semantickitti", "read_carla_ply", "CarlaCloud", "read_poses", "read_sequence",
           "psog_from_semantickitti", "write_semantickitti_sequence", "write_frame", "write_frame_bin",
           "frame_paths", "sensor_matrix", "pose_row", "atomic_write", "SEQUENCE_META", "prepare_sequence_folder",
           "read_sequence_metadata", "write_sequence_metadata", "sequence_spec"]
