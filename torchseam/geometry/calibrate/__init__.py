"""Calibration of the laser-vision sensor (METHOD.md section 7), one module per procedure.

Four procedures, each from a set of views, each returning a typed result with its residuals:

* :func:`calibrate_camera` (:mod:`.camera`): intrinsics and OpenCV distortion from checkerboard
  images (``findChessboardCorners`` + ``cornerSubPix`` + ``calibrateCameraExtended``).
* :func:`calibrate_laser_plane` (:mod:`.laser`): the laser light plane in {C} from stripe images
  on the flat board at several poses. The board pose comes from a checkerboard image taken at the
  same pose (``solvePnP``) or is given; the stripe centre line is found per column by sub-pixel
  grey gravity; the undistorted rays are cut with the board plane and a plane is fitted by SVD.
* :func:`calibrate_hand_eye` (:mod:`.handeye`): the camera pose in the flange {F} from recorded
  flange poses ``T_B_F`` and images of a board fixed in the robot base (``AX = XB``, Park &
  Martin, with ``cv2.calibrateHandEye`` where the installed OpenCV has it), refined by bundle
  adjustment of the corner reprojection error.
* :func:`calibrate_tcp` (:mod:`.tcp`): the torch tool centre point in {F} by pivoting: the torch
  tip touches one fixed point from several orientations; linear least squares.

:mod:`.sets` holds what they share: reading a set's image files, finding the board and its pose
in an image, and the checks that a set is usable. Each procedure's module also reads its own
folder layout (``load_*_set``); the robot pose file of the hand-eye and TCP sets is the
project's one pose CSV, read by :func:`torchseam.core.poses_csv.read_pose_csv` (the simulator
writes it with :func:`~torchseam.core.poses_csv.write_pose_csv`).
:mod:`.cellfile` writes a result into a cell config, keeping the file's comments; the
``torchseam calibrate`` command (:mod:`torchseam.geometry.calib_cli`) is the one that calls it.

A package, not ``calib_*.py`` modules beside :mod:`torchseam.geometry.calib_cli`: the name
``torchseam.geometry.calibrate`` stays the one import for callers (the names are re-exported
here), no name clashes (the package replaces the single module of the same name), and the
procedures' files sit together apart from geometry's run-time modules (triangulation, the torch
frame). The import graph inside is a tree: ``camera``, ``laser``, ``handeye`` and ``tcp`` import
only ``sets``, never each other, ``cellfile`` none of them, and none imports from this
``__init__``.

Settings live in ``configs/calibration.yaml`` (:class:`CalibrationConfig`). Every error names
what to fix: the image that failed, the view that is short, the set that is degenerate.

Frames: {B} robot base, {F} flange, {C} camera, {O} board (origin at the first inner corner,
x along the board's ``cols`` corners, y along its ``rows``, z into the board, away from the
camera that sees its face). Units: mm, degrees, pixels; quaternions (w, x, y, z).
"""

from __future__ import annotations

from torchseam.core.calibration import (
    BoardSpec,
    CalibrationConfig,
    CalibrationError,
    CameraSetSim,
    CameraSettings,
    DetectSettings,
    HandEyeSetSim,
    HandEyeSettings,
    LaserSetSim,
    LaserSettings,
    RenderSettings,
    SimulationSettings,
    TcpSetSim,
    TcpSettings,
    load_calibration,
)
from torchseam.geometry.calibrate.camera import CameraCalibration, calibrate_camera, load_camera_set
from torchseam.geometry.calibrate.cellfile import (
    load_calibrated_cell,
    splice_section,
    update_cell,
)
from torchseam.geometry.calibrate.handeye import (
    HAND_EYE_METHODS,
    HandEyeCalibration,
    calibrate_hand_eye,
    hand_eye_linear,
    load_handeye_set,
)
from torchseam.geometry.calibrate.laser import (
    LaserCalibration,
    calibrate_laser_plane,
    extract_stripe,
    fit_plane,
    load_laser_set,
    stripe_on_board,
)
from torchseam.geometry.calibrate.sets import (
    IMAGE_SUFFIXES,
    board_pose,
    detect_board,
    list_images,
    read_image,
    to_grey,
)
from torchseam.geometry.calibrate.tcp import TcpCalibration, calibrate_tcp, load_tcp_set

#: the settings live in :mod:`torchseam.core.calibration` (the simulator reads them too);
#: re-exported here with the procedures
__all__ = ["HAND_EYE_METHODS", "IMAGE_SUFFIXES", "BoardSpec", "CalibrationConfig",
           "CalibrationError", "CameraCalibration", "CameraSetSim", "CameraSettings",
           "DetectSettings", "HandEyeCalibration", "HandEyeSetSim", "HandEyeSettings",
           "LaserCalibration", "LaserSetSim", "LaserSettings", "RenderSettings",
           "SimulationSettings", "TcpCalibration", "TcpSetSim", "TcpSettings", "board_pose",
           "calibrate_camera", "calibrate_hand_eye", "calibrate_laser_plane", "calibrate_tcp",
           "detect_board", "extract_stripe", "fit_plane", "hand_eye_linear", "list_images",
           "load_calibrated_cell",
           "load_calibration", "load_camera_set", "load_handeye_set", "load_laser_set",
           "load_tcp_set", "read_image", "splice_section", "stripe_on_board",
           "to_grey", "update_cell"]
