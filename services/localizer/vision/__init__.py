"""Stereo Visual Teach & Repeat core (thesis ch. 2): pure code, no bus, no clocks.

camera (observation model) -> features (stereo keypoints) -> pose (registration against a submap)
-> teach_repeat (map building, repeat-phase localization) -> map_file (one file per route).
"""
from services.localizer.vision.camera import StereoCamera
from services.localizer.vision.features import StereoFrontend, StereoKeypoints
from services.localizer.vision.map_file import MapFileError, load_map, save_map
from services.localizer.vision.pose import PoseEstimate, estimate_pose
from services.localizer.vision.settings import VisionSettings
from services.localizer.vision.teach_repeat import (Keyframe, RepeatStep, TeachStep, VisionMap, VisualRepeat,
                                                     VisualTeach)

__all__ = ["StereoCamera", "StereoFrontend", "StereoKeypoints", "MapFileError", "load_map", "save_map",
           "PoseEstimate", "estimate_pose", "VisionSettings", "Keyframe", "RepeatStep", "TeachStep", "VisionMap",
           "VisualRepeat", "VisualTeach"]
