"""The calibration's names the command line's parser needs (``calibrate handeye --method``
choices), in a module that imports neither OpenCV nor scipy:
:mod:`torchseam.geometry.calibrate.handeye` solves with them."""

#: the closed-form hand-eye solvers by ``--method`` name: the name of OpenCV's flag for each
HAND_EYE_CV_FLAGS = {"tsai": "CALIB_HAND_EYE_TSAI", "park": "CALIB_HAND_EYE_PARK",
                     "horaud": "CALIB_HAND_EYE_HORAUD", "andreff": "CALIB_HAND_EYE_ANDREFF",
                     "daniilidis": "CALIB_HAND_EYE_DANIILIDIS"}
#: the ``method`` names :func:`torchseam.geometry.calibrate.calibrate_hand_eye` takes
HAND_EYE_METHODS = tuple(HAND_EYE_CV_FLAGS)
