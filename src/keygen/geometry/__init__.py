"""Geometry for keygen: rotations, rigid transforms, point clouds and pinhole cameras (NumPy only).

Conventions: SI units (metres, radians unless a name says ``deg``), world z-up, rotation
matrices act on column vectors, 6D rotations are the first two columns of the matrix,
quaternions are (w, x, y, z) as in MuJoCo and say so in their names, camera frames are OpenCV
(x right, y down, z forward) unless a name says OpenGL.
"""

from keygen.geometry.cameras import (
    backproject_depth,
    camera_points_to_world,
    fov_from_intrinsics,
    intrinsics_from_fov,
    look_at,
    opencv_to_opengl,
    opengl_to_opencv,
    project_points,
)
from keygen.geometry.clouds import (
    chamfer_distance,
    crop_box,
    farthest_point_sample,
    nearest_distances,
    normalize_cloud,
    random_subset,
    voxel_downsample,
)
from keygen.geometry.rotations import (
    axis_angle_to_matrix,
    is_rotation,
    matrix_to_axis_angle,
    matrix_to_quat_wxyz,
    matrix_to_rot6d,
    nearest_octahedral,
    octahedral_group,
    octahedral_index,
    octahedral_inverse_indices,
    octahedral_multiplication_table,
    quat_wxyz_to_matrix,
    random_rotation,
    rot6d_to_matrix,
    rotation_angle_between,
    yaw_matrix,
)
from keygen.geometry.transforms import (
    RigidTransform,
    apply_transform,
    compose,
    invert_transform,
    make_transform,
    pose_to_transform,
    transform_directions,
    transform_to_pose,
)

__all__ = [
    # rotations
    "axis_angle_to_matrix",
    "is_rotation",
    "matrix_to_axis_angle",
    "matrix_to_quat_wxyz",
    "matrix_to_rot6d",
    "nearest_octahedral",
    "octahedral_group",
    "octahedral_index",
    "octahedral_inverse_indices",
    "octahedral_multiplication_table",
    "quat_wxyz_to_matrix",
    "random_rotation",
    "rot6d_to_matrix",
    "rotation_angle_between",
    "yaw_matrix",
    # transforms
    "RigidTransform",
    "apply_transform",
    "compose",
    "invert_transform",
    "make_transform",
    "pose_to_transform",
    "transform_directions",
    "transform_to_pose",
    # point clouds
    "chamfer_distance",
    "crop_box",
    "farthest_point_sample",
    "nearest_distances",
    "normalize_cloud",
    "random_subset",
    "voxel_downsample",
    # cameras
    "backproject_depth",
    "camera_points_to_world",
    "fov_from_intrinsics",
    "intrinsics_from_fov",
    "look_at",
    "opencv_to_opengl",
    "opengl_to_opencv",
    "project_points",
]
