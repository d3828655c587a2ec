"""Your own recordings: one folder per session in a small documented format (``docs/own-data.md``).

A session folder holds::

    camera.json          image size, fx fy cx cy, optional OpenCV distortion, camera height (or "unknown")
    images/              the images (PNG, JPEG, BMP, GIF, WebP, TIFF, PNM)
    images.csv           optional: ``file,timestamp`` (file relative to the session folder, timestamp in s);
                         without it every image's name is its timestamp (``1327251905.811462.png``: seconds,
                         ``1327251905811462.png``: an integer in ``camera.json``'s ``name_time_unit``, default µs)
    poses_tum.txt        TUM RGB-D trajectory ``timestamp tx ty tz qx qy qz qw`` (camera-to-world, metres), or
    poses_kitti.txt      KITTI odometry poses: 12 numbers per line (row-major 3 × 4 camera-to-world), one per image
    depth/               optional: ``<image stem>.png`` (uint16 millimetres, 0 = missing) or ``.npy`` / ``.tiff``
                         (float32 metres), one per image
    odometry.csv         optional wheel odometry: ``timestamp,x,y,yaw`` (s, m, m, rad) or ``timestamp,travelled_m``

Typical use::

    from placejax.data import folder
    s = folder.load_session("/data/campus/january")
    print(s.report)                # kept / dropped frame counts
    s.image(0), s.poses[0]         # upright RGB uint8 (H, W, 3); x, y (m), yaw (rad)

Poses are interpolated to every image timestamp (position linearly, orientation by slerp) between the two
trajectory samples around it; an image before the first or after the last sample, or farther than
``tolerance_s`` from its nearest sample, is dropped and counted in :attr:`FolderSession.report`. Every other
defect raises :class:`FolderFormatError` whose message starts with ``file:line:`` (or ``file:`` when no line is
to blame): unsorted or duplicate timestamps, a missing or unreadable image, a NaN or non-unit quaternion, images
of different sizes, a missing camera field, an empty session, and every value beyond its bound or file beyond its
budget (:class:`FolderLimits` and the ``MAX_*`` constants: positions within 100 km, at most 50 m/s between
poses, timestamps up to 2**53 µs, 128 MiB and 2 million lines per text file, image headers checked against
``camera.json`` before decoding, ...).

The planar pose a session reports is ``(x, y, yaw)``: the camera position on the two horizontal world axes and
the heading of its optical axis (camera +z) measured from the first towards the second. ``camera.json``'s
``vertical_axis`` says which world axis is vertical: ``"z"`` (default; z up or down, as in TUM RGB-D, NCLT's
NED frame or any map frame), ``"y"`` (the first camera's frame of visual odometry, e.g. KITTI's ground truth:
horizontal axes z, x) or ``"x"``.

Modules behind this surface: ``_formats`` (timestamps, pose files, ``images.csv``, odometry), ``_camera_file``,
``_frames`` (image and depth files), ``_session``, ``_writing``, ``_limits``, ``_plausibility``; rotations,
slerp and interpolation are :mod:`placejax.data.poses`.
"""

from placejax.data.folder._camera_file import CAMERA_FILE, CAMERA_FILES, CameraSpec, read_camera
from placejax.data.folder._errors import FolderFormatError, MissingSessionError
from placejax.data.folder._formats import (
    IMAGE_SUFFIXES,
    IMAGE_TABLE,
    IMAGES_DIR,
    KITTI_FILE,
    ODOMETRY_FILE,
    QUATERNION_NORM_TOLERANCE,
    TUM_FILE,
    format_timestamp,
    images_from_names,
    parse_timestamp,
    read_image_table,
    read_kitti_poses,
    read_odometry,
    read_tum,
)
from placejax.data.folder._frames import DEPTH_DIR, DEPTH_SUFFIXES
from placejax.data.folder._limits import (
    FOCAL_RANGE,
    MAX_CAMERA_BYTES,
    MAX_CAMERA_HEIGHT_M,
    MAX_CAMERA_NESTING,
    MAX_COORDINATE_M,
    MAX_DISTORTION,
    MAX_IMAGES,
    MAX_LINE_BYTES,
    MAX_NAME_BYTES,
    MAX_ODOMETER_M,
    MAX_SPEED_MPS,
    MAX_TABLE_PATH_CHARS,
    MAX_TEXT_BYTES,
    MAX_TEXT_LINES,
    MAX_TIMESTAMP_US,
    MAX_YAW_RAD,
    PRINCIPAL_POINT_MARGIN,
    FolderLimits,
)
from placejax.data.folder._plausibility import trajectory_warnings
from placejax.data.folder._session import (
    FolderReport,
    FolderSession,
    load_session,
    load_sessions,
    require_sessions,
    session_folders,
)
from placejax.data.folder._writing import write_poses, write_session
from placejax.data.poses import (
    Trajectory,
    interpolate_poses,
    matrix_to_quaternion,
    planar_poses,
    quaternion_to_matrix,
)

__all__ = [
    "CAMERA_FILE",
    "CAMERA_FILES",
    "DEPTH_DIR",
    "DEPTH_SUFFIXES",
    "FOCAL_RANGE",
    "IMAGES_DIR",
    "IMAGE_SUFFIXES",
    "IMAGE_TABLE",
    "KITTI_FILE",
    "MAX_CAMERA_BYTES",
    "MAX_CAMERA_HEIGHT_M",
    "MAX_CAMERA_NESTING",
    "MAX_COORDINATE_M",
    "MAX_DISTORTION",
    "MAX_IMAGES",
    "MAX_LINE_BYTES",
    "MAX_NAME_BYTES",
    "MAX_ODOMETER_M",
    "MAX_SPEED_MPS",
    "MAX_TABLE_PATH_CHARS",
    "MAX_TEXT_BYTES",
    "MAX_TEXT_LINES",
    "MAX_TIMESTAMP_US",
    "MAX_YAW_RAD",
    "ODOMETRY_FILE",
    "PRINCIPAL_POINT_MARGIN",
    "QUATERNION_NORM_TOLERANCE",
    "TUM_FILE",
    "CameraSpec",
    "FolderFormatError",
    "FolderLimits",
    "FolderReport",
    "FolderSession",
    "MissingSessionError",
    "Trajectory",
    "format_timestamp",
    "images_from_names",
    "interpolate_poses",
    "load_session",
    "load_sessions",
    "matrix_to_quaternion",
    "parse_timestamp",
    "planar_poses",
    "quaternion_to_matrix",
    "read_camera",
    "read_image_table",
    "read_kitti_poses",
    "read_odometry",
    "read_tum",
    "require_sessions",
    "session_folders",
    "trajectory_warnings",
    "write_poses",
    "write_session",
]
