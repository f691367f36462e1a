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


def test_library_names_become_the_flags_of_the_command():
    from ceilkit.cli.common import as_flags
    from ceilkit.runtime.errors import ConfigError

    def shown(key, command="", takes_option=False, path=None):
        return str(as_flags(ConfigError(path, key, "what"), command, takes_option))

    assert shown("method") == "--method: what"
    assert shown("board", "intrinsics") == "--board: what"
    assert shown("y_m", "simulate") == "--lateral: what"
    assert shown("options.noise_sigma", "simulate") == "--noise: what"
    assert shown("options.detector", "replay", takes_option=True) == "--option detector: what"
    assert shown("options.detector") == "options.detector: what"  # no --option there
    assert shown("mount.tilt", path="rig.yaml") == "rig.yaml: mount.tilt: what"  # a file's key
    assert shown("method", path="x.yaml") == "x.yaml: method: what"


def test_option_items_are_parsed_and_bad_ones_named():
    import pytest

    from ceilkit.cli.common import parse_options
    from ceilkit.runtime.errors import ConfigError

    assert parse_options(["detector=lsd", " min_contrast = 4 "]) == {
        "detector": "lsd", "min_contrast": "4"}
    assert parse_options(None) == {} and parse_options(["note=a=b"]) == {"note": "a=b"}
    for bad, words in ((["detector"], "expected KEY=VALUE"), (["=1"], "expected KEY=VALUE"),
                       (["a=1", "a=2"], "a given twice")):
        with pytest.raises(ConfigError, match=words) as err:
            parse_options(bad)
        assert err.value.key == "--option"
