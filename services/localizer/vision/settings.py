"""Every tunable of the stereo VT&R core in one frozen dataclass (defaults tuned on KITTI odometry).

Pixel quantities are at the input image's resolution. Measurement noise is given for octave 0; an
ORB keypoint found on pyramid level o is `orb_scale**o` times less precise in (u, v).
"""
from __future__ import annotations

from dataclasses import dataclass

from common.path import DEFAULT_SPACING_M


@dataclass(frozen=True, kw_only=True)
class VisionSettings:
    # --- feature extraction (ORB on both images, then bucketing on the left image)
    orb_max_detect: int = 20000       # a cap only: FAST's threshold decides, bucketing thins out
    orb_levels: int = 4
    orb_scale: float = 1.2
    orb_fast_threshold: int = 20
    orb_harris: bool = False          # rank by Harris score (as ORB does) or by the cheaper FAST score
    orb_edge: int = 19                # border (px) without keypoints, must cover the ORB patch
    grid_rows: int = 6
    grid_cols: int = 16
    per_cell: int = 16                # left keypoints kept per grid cell (strongest score)
    right_per_cell: int = 32          # right image: more, its cells are shifted by the disparity
    # --- left-right association along rectified rows
    max_dv_px: float = 2.0
    d_min_px: float = 1.0
    d_max_px: float = 160.0
    max_octave_gap: int = 1
    stereo_max_hamming: int = 60
    stereo_ratio: float = 0.85        # best / second best Hamming distance among the row candidates
    subpixel_radius_px: int = 2       # patch search +-r around the descriptor disparity
    subpixel_half_patch: int = 3      # 7x7 SAD patch
    # --- measurement noise (std, octave 0), the weights W_n of eq. 2.4
    sigma_uv_px: float = 0.6
    sigma_d_px: float = 0.6
    # --- matching against a reference (previous frame, keyframe submap)
    match_max_hamming: int = 64
    match_ratio: float = 0.85
    gate_px: float = 40.0             # with a prior pose: |predicted - measured| (u, v) window
    # --- outlier rejection and Gauss-Newton (eq. 2.3-2.4)
    ransac_iters: int = 200
    ransac_px: float = 2.5
    ransac_confidence: float = 0.999
    gn_iters: int = 12
    gn_rounds: int = 3                # re-select inliers on the full (u, v, d) error between rounds
    inlier_chi2: float = 16.0         # squared Mahalanobis distance (3 dof) of an inlier
    huber_k: float = 2.0              # robust weight beyond k sigma
    min_inliers: int = 25             # below this an estimate is refused, never fabricated
    # --- teach: map building
    keyframe_dist_m: float = DEFAULT_SPACING_M
    keyframe_angle_deg: float = 5.0
    ba_window: int = 5                # keyframes adjusted together (window_ba.py); < 2: no adjustment
    ba_iters: int = 2                 # Levenberg-Marquardt iterations (Huber) per new keyframe, then one Cauchy
    ba_max_landmarks: int = 200       # landmarks per window, longest tracks first (0: all)
    submap_augment: bool = True       # features tracked between keyframes join the keyframe's submap
    estimate_disparity_offset: bool = True   # self-calibrate the rig's constant disparity error
    disparity_offset_prior_px: float = 1.0   # std of its prior (mean 0) before the first window
    # --- repeat
    search_radius: int = 5            # keyframes either side of the hint tried at start / after loss
    nearest_window: int = 3           # keyframes either side of the current one eligible as nearest
    max_vo_frames: int = 10           # consecutive frames without a keyframe refinement before "lost"
    vo_sigma_m: float = 0.01          # per-frame VO covariance floor (std) added while dead-reckoning
    vo_sigma_deg: float = 0.2
    jump_gate_m: float = 0.3          # refinement vs VO prediction: larger disagreement is rejected
    jump_gate_deg: float = 3.0
