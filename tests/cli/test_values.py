"""Every numeric flag of every command, from the CLI's own parameter table: NaN,
infinities, a value below its range, a negative one and a huge one are each refused
in one line naming the flag as typed, with the range, before anything runs
(cli/values.py). A new numeric flag gets these cases without a line of test; one
without a declared range fails here."""

from __future__ import annotations

import pytest
import typer.main
from typer.testing import CliRunner

from ceilkit.cli.ceilcal import app as ceilcal_app
from ceilkit.cli.ceilrun import app as ceilrun_app
from ceilkit.cli.values import OWN_CHECKS, flag_name, numeric_kind, range_of

run = CliRunner().invoke


@pytest.fixture(scope="module", autouse=True)
def _apps_built_once():
    """Each app's click commands built once for the module's ~250 invocations (typer
    rebuilds them on every invocation otherwise: most of the time of a case)."""
    import typer.testing

    build, built = typer.testing._get_command, {}
    typer.testing._get_command = lambda app: built.setdefault(id(app), build(app))
    yield
    typer.testing._get_command = build


def _commands():
    """``(prog, app, command name or "", click command)`` of both command lines."""
    for prog, app in (("ceilrun", ceilrun_app), ("ceilcal", ceilcal_app)):
        top = typer.main.get_command(app)
        yield prog, app, "", top
        for name, cmd in top.commands.items():
            yield prog, app, name, cmd


def _numeric_flags():
    for prog, app, name, cmd in _commands():
        for p in cmd.params:
            if numeric_kind(p) is not None:
                yield prog, app, name, cmd, p


def _valid(span, kind) -> str:
    return str(int(span.hi)) if kind is int else f"{span.hi:g}"


def _required_args(cmd, name) -> list[str]:
    """A value for each required parameter of ``cmd`` (a number inside its range, a
    word otherwise): enough to parse, nothing runs before the values are checked."""
    out: list[str] = []
    for p in cmd.params:
        if not getattr(p, "required", False):
            continue
        kind, flag = numeric_kind(p), flag_name(p)
        value = _valid(range_of(name, flag), kind) if kind else "x"
        out += [value] if p.param_type_name == "argument" else [flag, value]
    return out


def _bad_values(span, kind) -> list[str]:
    """Texts outside ``span`` (of ``kind``): not finite, below, negative, huge."""
    bad = ["nan", "inf"] if kind is float else []
    below = span.lo if span.lo_open else span.lo - 1
    bad.append(str(int(below)) if kind is int else repr(float(below)))
    if span.lo >= 0:
        bad.append("-1")
    bad.append("99999999999999999999" if kind is int else "1e308")
    return list(dict.fromkeys(bad))


CASES = [pytest.param(prog, app, name, cmd, p,
                      id=f"{prog} {name} {flag_name(p)}".replace("  ", " "))
         for prog, app, name, cmd, p in _numeric_flags() if name not in OWN_CHECKS]


def test_the_table_walks_every_command():
    flags = {(name, flag_name(p)) for _, _, name, _, p in _numeric_flags()}
    assert ("", "--baud") in flags and ("replay", "--baud") in flags
    assert ("intrinsics", "--min-views") in flags and ("mount", "--max-frames") in flags
    assert len(CASES) >= 50


@pytest.mark.parametrize("prog,app,name,cmd,param", CASES)
def test_every_numeric_flag_refuses_bad_values_in_one_line(prog, app, name, cmd, param):
    flag, kind = flag_name(param), numeric_kind(param)
    span = range_of(name, flag)
    assert span is not None, f"{prog} {name} {flag}: declare its range in cli/values.py RANGES"
    assert span.lo < span.hi and span.hi < 1e300, "a range is finite"
    head = [name] if name else []
    for text in _bad_values(span, kind):
        res = run(app, [*head, *_required_args(cmd, name), f"{flag}={text}"])
        lines = res.stderr.strip().splitlines()
        assert res.exit_code in (1, 2), (flag, text, res.output)
        assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
        assert len(lines) == 1, (flag, text, res.stderr)
        assert lines[0].startswith(f"{prog}: error: {flag}: expected "), (text, lines[0])
        assert span.expected(kind is int) in lines[0], lines[0]


@pytest.mark.parametrize("args,line", [
    (["--view-token", ""], "ceilrun: error: --view-token: expected a value, found an empty "
                           "string"),
    (["--method", ""], "ceilrun: error: --method: expected a value, found an empty string"),
    (["--view-token", "  "], "ceilrun: error: --view-token: expected a value, found '  '"),
    (["--serial", ""], "ceilrun: error: --serial: expected a value, found an empty string"),
    (["replay", "REC", "--method="], "ceilrun: error: --method: expected a value, found an "
                                     "empty string"),
    (["--fourcc", "TOOLONG", "--device", "sim:corridor", "--frames", "1"],
     "ceilrun: error: --fourcc: expected 4 characters (MJPG, YUYV, ...) or nothing (the "
     "driver's), found 'TOOLONG'"),
    (["--frames", "nan"], "ceilrun: error: --frames: expected an integer in [0, 100000000] "
                          "frames (0: until stopped), found 'nan'"),
    (["--no-such-flag"], "ceilrun: error: No such option: --no-such-flag"),
])
def test_strings_and_usage_errors_are_one_line(args, line):
    res = run(ceilrun_app, args)
    assert res.exit_code in (1, 2)
    assert res.stderr.strip().splitlines() == [line]


def test_an_empty_value_that_means_something_is_taken():
    from ceilkit.cli.values import EMPTY_OK

    flags = {flag_name(p) for *_, p in _numeric_flags()}
    assert not flags & EMPTY_OK   # EMPTY_OK names string flags only
    res = run(ceilrun_app, ["--fourcc", "", "--ros2-namespace", "", "--fsync-every", "-1"])
    assert res.stderr.strip().splitlines() == [   # the first refused is the one after them
        "ceilrun: error: --fsync-every: expected a number in [0, 3600] s (0: off), found -1"]


@pytest.mark.parametrize("args,line", [
    (["--device", "sim:corridor", "--frames", "1", "--start-pose", "1,2"],
     "ceilrun: error: --start-pose: expected X,Y,YAW (m, m, degrees) or "
     "X,Y,YAW,SIGMA_M,SIGMA_DEG, found '1,2'"),
    (["--device", "sim:corridor", "--frames", "1", "--view", "abc"],
     "ceilrun: error: --view: expected [HOST:]PORT, found 'abc'"),
    (["--device", "sim:corridor", "--frames", "1", "--max-speed", "nan"],
     "ceilrun: error: --max-speed: expected a speed in (0, 100] m/s and a turn rate in "
     "(0, 3600] degrees/s, found 'nan'"),
    (["--device", "sim:corridor", "--frames", "1", "--max-speed", "2,x"],
     "ceilrun: error: --max-speed: expected SPEED (m/s) or SPEED,TURN (m/s, degrees/s), "
     "found '2,x'"),
])
def test_a_library_parameter_is_named_by_its_flag(args, line):
    res = run(ceilrun_app, args)
    assert res.exit_code == 1 and res.stderr.strip().splitlines() == [line]


def test_library_names_map_to_the_commands_own_flags():
    from ceilkit.cli.common import as_flags
    from ceilkit.runtime.errors import ConfigError

    def shown(key, command):
        top = typer.main.get_command(ceilcal_app if command in ("lightmap", "exposure")
                                     else ceilrun_app)
        cmd = top.commands.get(command, top)
        return str(as_flags(ConfigError(None, key, "what"), command, params=cmd.params))

    assert shown("start_pose", "") == "--start-pose: what"
    assert shown("wheel_track_m", "") == "--wheel-track: what"
    assert shown("fsync_every_s", "") == "--fsync-every: what"
    assert shown("ceiling_height_m", "lightmap") == "--ceiling-height: what"
    assert shown("anchor_frame", "lightmap") == "--anchor-frame: what"
    assert shown("exposures", "exposure") == "--exposures: what"
    assert shown("recording", "replay") == "RECORDING: what"
    assert shown("link", "replay") == "--serial: what"           # FLAGS, no such param
    assert shown("no_such_name", "replay") == "no_such_name: what"


def test_every_range_is_in_the_cli_reference():
    from helpers import ROOT

    rows = [ln for ln in (ROOT / "docs" / "cli.md").read_text().splitlines()
            if ln.startswith("| `--")]
    for *_, name, _cmd, p in (c.values for c in CASES):
        flag, kind = flag_name(p), numeric_kind(p)
        want = range_of(name, flag).expected(kind is int)
        assert any(r.startswith(f"| `{flag}` |") and r.endswith(f"| {want} |") for r in rows), \
            f"docs/cli.md: no row `| `{flag}` | ... | {want} |`"


def test_an_error_during_intrinsics_progress_starts_its_own_line(capsys):
    from ceilkit.cli.ceilcal_intrinsics import _MeterLine, _progress
    from ceilkit.cli.common import echo_err

    _progress(0, 3, "img0.png", True)          # detecting 1/3, the line left open
    echo_err("ceilcal: error: img1.png: mixed image sizes")
    meter = _MeterLine()
    meter.write("\rviews 3, position 40%")      # the live coverage meter, left open
    echo_err("ceilcal: error: camera lost")
    lines = capsys.readouterr().err.split("\n")
    assert "ceilcal: error: img1.png: mixed image sizes" in lines
    assert "ceilcal: error: camera lost" in lines
    assert lines[0].startswith("\rdetecting 1/3 img0.png")


def test_a_coordinate_typed_as_text_is_bounded():
    from ceilkit.cli.ceilcal_lightmap import parse_xy
    from ceilkit.runtime.errors import ConfigError

    for text in ("1e308,0", "0,-2e6", "inf,0"):
        with pytest.raises(ConfigError) as err:
            parse_xy(text, "--known-light")
        assert str(err.value) == (f"--known-light: expected finite X,Y in metres, each in "
                                  f"[-1e+06, 1e+06], found {text!r}")
