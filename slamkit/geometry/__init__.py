"""Geometry, vectorised, each formula in one place: rigid transforms and projection
(`transforms`, re-exported here), Gaussian covariances (`gaussians`), global registration
(`registration`), pose graphs (`pose_graph`) and the map's surface agreement with a frame
(`surface`)."""

from slamkit.geometry.transforms import (
                                         backproject,
                                         covariance_from_scales,
                                         invert_pose,
                                         make_pose,
                                         motion_power,
                                         nearest_rotation,
                                         pixel_grid,
                                         project_points,
                                         quat_left_matrix,
                                         quat_to_rotmat,
                                         rotation_angle_deg,
                                         rotmat_to_quat,
                                         scales_from_covariance,
                                         se3_exp,
                                         skew,
                                         so3_exp,
                                         so3_log,
                                         transform_points,
)

__all__ = ["backproject", "covariance_from_scales", "invert_pose", "make_pose", "motion_power", "nearest_rotation",
           "pixel_grid", "project_points", "quat_left_matrix", "quat_to_rotmat", "rotation_angle_deg", "rotmat_to_quat",
           "scales_from_covariance", "se3_exp", "skew", "so3_exp", "so3_log", "transform_points"]
