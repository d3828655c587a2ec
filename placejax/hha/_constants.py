"""Constants of the HHA encoding (Gupta et al., ECCV 2014; values of the original code, ``docs/hha.md``)."""

RADIUS_ANGLE = 3
"""Half-width of the 7 × 7 windows whose plane fits give the normals of the angle channel."""
RADIUS_GRAVITY = 10  # 21×21 normals feed only the gravity estimate
GRAVITY_THRESHOLDS_DEG = (45.0, 15.0)  # floor/wall thresholds of the two passes
GRAVITY_ITERATIONS = (5, 5)
ROTATION_SKIP_DEG = 0.1  # no rotation when gravity is this close to the image's down axis
FLOOR_RULE_CM = -90.0  # if the lowest point is less than 0.9 m below the camera ...
FLOOR_FALLBACK_CM = -130.0  # ... assume the floor 1.3 m below it
DISPARITY_NUMERATOR = 31000.0  # disparity = 31000 / max(Z_cm, 100)
DISPARITY_MIN_CM = 100.0
ANGLE_OFFSET = 38.0  # angle channel = θ + 38 (floor ≈ 38, wall ≈ 128)
ANGLE_NAN_DEG = 180.0  # angle where the normal is undefined
# Valid depth range (m, inclusive), the encoder's defaults. Below 0.1 m no depth sensor or monocular mapping gives
# a usable value, and a single such pixel (1e-9 m of sensor junk) moves the gravity estimate and so most heights
# and angles of the image; 1000 m keeps the farthest plausible outdoor surfaces (and SimCampus's sky depth,
# exactly 1000 m) while overflow junk such as 1e30 counts as missing.
MIN_DEPTH_M = 0.1
MAX_DEPTH_M = 1000.0
"""The encoder's farthest valid depth (m): SimCampus's sky, and where far predictions are handed over as sky."""
