"""Configuration of the simulated stereo camera: shared by the scenario file and the bridge."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True, kw_only=True)
class StereoConfig:
    """The simulated rectified stereo camera (rendered by services/bridge/render.py); the scenario's
    [localization.camera], used when localization.source = "vision"."""
    width_px: int = 640                 # image width (both cameras)
    height_px: int = 480                # image height (both cameras)
    hfov_deg: float = 75.0              # horizontal field of view; square pixels, principal point at the centre
    baseline_m: float = 0.24            # distance between the left and right optical centres
    mount_x_m: float = 0.3              # rig centre (midway between the cameras) ahead of the robot origin
    mount_z_m: float = 0.7              # rig centre above the ground
    pitch_deg: float = 12.0             # camera tilt below the horizon (positive looks down)
    exposure_s: float = 0.008           # exposure time: sets the motion blur at speed and turn rate
    vibration_radps_per_mps: float = 0.3  # random body pitch/roll rate per m/s of speed (bumps): more blur when fast
    noise_dn: float = 2.0               # std of the additive sensor noise in grey levels (0-255)
    lighting_change: float = 0.0        # 0..1: how much gain, offset, shading and cloud shadows differ per trial
    landmark_density: float = 3.0       # landmarks (rocks, trunks, walls, fences) per 100 m^2 of the 1.5-20 m band
    encoding: Literal["mono8", "png"] = "mono8"  # image payload: raw uint8 rows or PNG files

    def __post_init__(self):
        if self.width_px < 16 or self.height_px < 16:
            raise ValueError("stereo images must be at least 16x16 px")
        if self.width_px * self.height_px > 1_500_000:
            raise ValueError("stereo images above 1.5 Mpx do not fit a StereoFrame message")
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise ValueError("hfov_deg must be in [10, 150]")
        if self.baseline_m <= 0 or self.mount_z_m <= 0:
            raise ValueError("baseline_m and mount_z_m must be > 0")
        if not -30.0 <= self.pitch_deg <= 60.0:
            raise ValueError("pitch_deg must be in [-30, 60]")
        if min(self.exposure_s, self.noise_dn, self.landmark_density, self.vibration_radps_per_mps) < 0:
            raise ValueError("exposure_s, noise_dn, landmark_density and vibration_radps_per_mps must be >= 0")
        if not 0.0 <= self.lighting_change <= 1.0:
            raise ValueError("lighting_change must be in [0, 1]")
