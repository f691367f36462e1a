"""cli/common.py: what every command line shares."""

import cv2.utils.logging as cv_logging

from ceilkit.cli.common import quiet_opencv


def test_quiet_opencv_keeps_only_errors():
    before = cv_logging.getLogLevel()
    try:
        cv_logging.setLogLevel(cv_logging.LOG_LEVEL_WARNING)
        quiet_opencv()
        assert cv_logging.getLogLevel() == cv_logging.LOG_LEVEL_ERROR
    finally:
        cv_logging.setLogLevel(before)
