"""Scenes (issue 36): a lidar and several targets, static or moving, scanned into labelled
clouds and sequences. This package is the numpy-only part: scene files (``spec.py``), poses
and their frames (``poses.py``), trajectories (``trajectory.py``), scan patterns
(``scan.py``) and the sequence format's reader (``sequence.py``). The scanning itself, on the
simulator's ray casters, is ``dataset_builder/scene.py``."""

from .poses import angles_of_poses, flight_matrices, poses_from_angles, turn
from .scan import PATTERNS, Groups, make_pattern
from .sequence import Frame, Sequence, load_sequence, read_frame
from .spec import Scene, SceneTarget, load_scene, scene_from_dict, scene_warnings
from .trajectory import ENVELOPES, KINDS, make_trajectory

__all__ = ["ENVELOPES", "KINDS", "PATTERNS", "Frame", "Groups", "Scene", "SceneTarget",
           "Sequence", "load_sequence", "read_frame",
           "angles_of_poses", "flight_matrices", "load_scene", "make_pattern",
           "make_trajectory", "poses_from_angles", "scene_from_dict", "scene_warnings", "turn"]
