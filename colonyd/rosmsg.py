"""ROS 2 messages (rosbags classes) built from numpy: headers, transforms, scans, depth images,
odometry, and the colony's outputs (occupancy grid, coloured cloud, object markers)."""

from __future__ import annotations

from typing import Any

import numpy as np

from plugins import rmw
from voxel.rotation import matrix_to_quaternion

#: PointField datatypes.
FLOAT32, UINT32 = 7, 6


def _t(name: str) -> Any:
    return rmw.typestore().types[name]


def header(stamp: float, frame_id: str) -> Any:
    """std_msgs/Header at `stamp` seconds (rounded to the nanosecond)."""
    ns = round(stamp * 1e9)
    time = _t("builtin_interfaces/msg/Time")(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    return _t("std_msgs/msg/Header")(stamp=time, frame_id=frame_id)


def pose_msg(pose: np.ndarray) -> Any:
    """geometry_msgs/Pose of a 4x4 transform."""
    q = matrix_to_quaternion(pose[:3, :3])
    point = _t("geometry_msgs/msg/Point")(
        x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])
    )
    quat = _t("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3])
    return _t("geometry_msgs/msg/Pose")(position=point, orientation=quat)


def transform_stamped(stamp: float, parent: str, child: str, pose: np.ndarray) -> Any:
    """geometry_msgs/TransformStamped: parent-from-child `pose` (4x4)."""
    q = matrix_to_quaternion(pose[:3, :3])
    v = _t("geometry_msgs/msg/Vector3")(
        x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])
    )
    quat = _t("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3])
    return _t("geometry_msgs/msg/TransformStamped")(
        header=header(stamp, parent),
        child_frame_id=child,
        transform=_t("geometry_msgs/msg/Transform")(translation=v, rotation=quat),
    )


def tf_message(transforms: list[Any]) -> Any:
    return _t("tf2_msgs/msg/TFMessage")(transforms=transforms)


def odometry(stamp: float, parent: str, child: str, pose: np.ndarray) -> Any:
    """nav_msgs/Odometry of the body `child` in `parent` (zero twist, zero covariance)."""
    zero = _t("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
    return _t("nav_msgs/msg/Odometry")(
        header=header(stamp, parent),
        child_frame_id=child,
        pose=_t("geometry_msgs/msg/PoseWithCovariance")(
            pose=pose_msg(pose), covariance=np.zeros(36)
        ),
        twist=_t("geometry_msgs/msg/TwistWithCovariance")(
            twist=_t("geometry_msgs/msg/Twist")(linear=zero, angular=zero),
            covariance=np.zeros(36),
        ),
    )


def laser_scan(
    stamp: float,
    frame_id: str,
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_max: float,
    range_min: float = 0.0,
) -> Any:
    """sensor_msgs/LaserScan (float32 ranges, no intensities)."""
    n = len(ranges)
    return _t("sensor_msgs/msg/LaserScan")(
        header=header(stamp, frame_id),
        angle_min=angle_min,
        angle_max=angle_min + angle_increment * (n - 1),
        angle_increment=angle_increment,
        time_increment=0.0,
        scan_time=0.0,
        range_min=range_min,
        range_max=range_max,
        ranges=np.asarray(ranges, np.float32),
        intensities=np.zeros(0, np.float32),
    )


def depth_image(stamp: float, frame_id: str, depth: np.ndarray) -> Any:
    """sensor_msgs/Image of a (H, W) depth image: uint16 as 16UC1, float32 as 32FC1."""
    h, w = depth.shape
    if depth.dtype == np.uint16:
        encoding, data = "16UC1", depth.astype("<u2")
    else:
        encoding, data = "32FC1", depth.astype("<f4")
    return _t("sensor_msgs/msg/Image")(
        header=header(stamp, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * data.itemsize,
        data=np.frombuffer(data.tobytes(), np.uint8),
    )


def camera_info(stamp: float, frame_id: str, K: np.ndarray, width: int, height: int) -> Any:
    """sensor_msgs/CameraInfo of a pinhole camera without distortion."""
    P = np.zeros((3, 4))
    P[:3, :3] = K
    roi = _t("sensor_msgs/msg/RegionOfInterest")(
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return _t("sensor_msgs/msg/CameraInfo")(
        header=header(stamp, frame_id),
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=np.asarray(K, np.float64).reshape(9),
        r=np.eye(3).reshape(9),
        p=P.reshape(12),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def point_cloud(stamp: float, frame_id: str, xyz: np.ndarray, rgb: np.ndarray | None) -> Any:
    """sensor_msgs/PointCloud2 of (N, 3) points, with packed `rgb` (N, 3) uint8 if given."""
    n = len(xyz)
    names = ["x", "y", "z"] + (["rgb"] if rgb is not None else [])
    field = _t("sensor_msgs/msg/PointField")
    fields = [field(name=nm, offset=4 * i, datatype=FLOAT32, count=1) for i, nm in enumerate(names)]
    rows = np.zeros((n, len(names)), np.float32)
    rows[:, :3] = xyz
    if rgb is not None:
        packed = (
            (rgb[:, 0].astype(np.uint32) << 16)
            | (rgb[:, 1].astype(np.uint32) << 8)
            | rgb[:, 2].astype(np.uint32)
        )
        rows[:, 3] = packed.view(np.float32)
    step = 4 * len(names)
    return _t("sensor_msgs/msg/PointCloud2")(
        header=header(stamp, frame_id),
        height=1,
        width=n,
        fields=fields,
        is_bigendian=False,
        point_step=step,
        row_step=step * n,
        data=np.frombuffer(rows.tobytes(), np.uint8),
        is_dense=True,
    )


def occupancy_grid(
    stamp: float, frame_id: str, cells: np.ndarray, resolution: float, origin: np.ndarray
) -> Any:
    """nav_msgs/OccupancyGrid of (H, W) int8 cells (-1 unknown, 0..100), row 0 at `origin`
    (x, y, z)."""
    h, w = cells.shape
    pose = np.eye(4)
    pose[:3, 3] = origin
    info = _t("nav_msgs/msg/MapMetaData")(
        map_load_time=header(stamp, "").stamp,
        resolution=resolution,
        width=w,
        height=h,
        origin=pose_msg(pose),
    )
    return _t("nav_msgs/msg/OccupancyGrid")(
        header=header(stamp, frame_id),
        info=info,
        data=np.ascontiguousarray(cells, np.int8).reshape(-1),
    )


def sphere_markers(
    stamp: float, frame_id: str, namespace: str, positions: np.ndarray, ids: list[int], size: float
) -> Any:
    """visualization_msgs/MarkerArray: a DELETEALL, then one sphere per position with its id."""
    marker = _t("visualization_msgs/msg/Marker")
    colour = _t("std_msgs/msg/ColorRGBA")
    vec = _t("geometry_msgs/msg/Vector3")
    duration = _t("builtin_interfaces/msg/Duration")(sec=0, nanosec=0)

    def make(i: int, action: int, pose: np.ndarray) -> Any:
        return marker(
            header=header(stamp, frame_id),
            ns=namespace,
            id=i,
            type=2,  # SPHERE
            action=action,
            pose=pose_msg(pose),
            scale=vec(x=size, y=size, z=size),
            color=colour(r=1.0, g=0.4, b=0.0, a=0.9),
            lifetime=duration,
            frame_locked=False,
            points=[],
            colors=[],
            texture_resource="",
            texture=_t("sensor_msgs/msg/CompressedImage")(
                header=header(stamp, ""), format="", data=np.zeros(0, np.uint8)
            ),
            uv_coordinates=[],
            text="",
            mesh_resource="",
            mesh_file=_t("visualization_msgs/msg/MeshFile")(
                filename="", data=np.zeros(0, np.uint8)
            ),
            mesh_use_embedded_materials=False,
        )

    markers = [make(0, 3, np.eye(4))]  # DELETEALL: objects that went away go from RViz too
    for i, p in zip(ids, positions, strict=True):
        pose = np.eye(4)
        pose[:3, 3] = p
        markers.append(make(int(i), 0, pose))
    return _t("visualization_msgs/msg/MarkerArray")(markers=markers)
