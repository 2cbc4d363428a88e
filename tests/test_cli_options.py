"""Every numeric option of every ``jaxloc`` subcommand is checked where it is parsed.

The options are enumerated from :func:`jaxloc.cli.build_parser` itself (its actions, its
subcommands and theirs), so an option added later is covered without editing this file: each
must have a checker of :mod:`jaxloc.cli._options` (or integer ``choices``), and given 0, a negative
number or NaN, ``jaxloc.cli.main`` must return exit status 2 after exactly one line on stderr that
names the option, or accept the value. Accepted values are not run where that would be heavy: a
command with positional files is run on files that do not exist (it must fail on them, in one
line, after its option checks), one without files only goes through the parser and
:func:`jaxloc.cli.check_args`. Nothing here compiles.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import pytest

from jaxloc.camera import stride_grid_shape
from jaxloc.cli import build_parser, check_args, main
from jaxloc.cli._demo import fitting_strides
from jaxloc.cli._errors import InputError
from jaxloc.cli._options import Parser
from jaxloc.sg2loc import SG2LocConfig
from jaxloc.sg2loc._scores import SSIM_WINDOW

#: The values every numeric option is tried with.
VALUES = ("0", "-3", "nan")


def _commands(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """``(path, parser)`` of the parser and of every subcommand below it, depth first."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, (*path, name))


def _leaves() -> list[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """The commands that run something (no subcommands of their own)."""
    return [
        (path, parser)
        for path, parser in _commands(build_parser())
        if path and not any(isinstance(a, argparse._SubParsersAction) for a in parser._actions)
    ]


def _is_numeric(action: argparse.Action) -> bool:
    """An option that takes a number: a ``type`` other than text or a path, integer choices, or
    a numeric default (an option that forgot its ``type=`` would read "0" as text)."""
    if not action.option_strings or action.nargs == 0:
        return False
    if action.type not in (None, str, Path):
        return True
    if action.choices is not None and all(isinstance(c, int) for c in action.choices):
        return True
    defaults = action.default if isinstance(action.default, list | tuple) else [action.default]
    return any(isinstance(d, int | float) and not isinstance(d, bool) for d in defaults)


def _numeric_options() -> list[tuple[tuple[str, ...], argparse.ArgumentParser, argparse.Action]]:
    return [
        (path, parser, action)
        for path, parser in _leaves()
        for action in parser._actions
        if _is_numeric(action)
    ]


def _option_name(action: argparse.Action) -> str:
    return max(action.option_strings, key=len)


def _values(action: argparse.Action, value: str) -> list[str]:
    """``value`` as many times as the option takes values."""
    return [value] * (action.nargs if isinstance(action.nargs, int) else 1)


def _needed(parser: argparse.ArgumentParser, root: Path) -> list[str]:
    """The positional arguments (paths that do not exist) and required options of a command."""
    argv = []
    for action in parser._actions:
        if not action.option_strings:
            argv += [str(root / f"missing_{action.dest}")] * (
                action.nargs if isinstance(action.nargs, int) else 1
            )
        elif action.required:
            argv += [action.option_strings[0], str(next(iter(action.choices)))]
    return argv


CASES = [
    pytest.param(path, action.dest, value, id=f"{' '.join(path)} {_option_name(action)} {value}")
    for path, _, action in _numeric_options()
    for value in VALUES
]


def _lookup(path: tuple[str, ...], dest: str):
    for leaf_path, parser in _leaves():
        if leaf_path == path:
            return parser, next(a for a in parser._actions if a.dest == dest)
    raise KeyError(path)


def _one_line(err: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n") and "Traceback" not in err, err
    return lines[0]


# ----------------------------------------------------------------------------- the enumeration


def test_every_command_parser_has_one_line_errors():
    for path, parser in _commands(build_parser()):
        assert isinstance(parser, Parser), path
        assert parser.prog == " ".join(["jaxloc", *path])


@pytest.mark.parametrize(
    "argv", [[], ["bench", "nothing"], ["demo", "--nope"], ["localize-lidar", "map"]]
)
def test_usage_errors_are_one_line(argv, capsys):
    assert main(argv) == 2  # returned, not raised
    out, err = capsys.readouterr()
    assert out == "" and ": error: " in _one_line(err)


def test_the_enumeration_sees_every_command_and_option():
    found = {(*path, _option_name(action)) for path, _, action in _numeric_options()}
    for expected in [
        ("demo", "--particles"),
        ("demo", "--strides"),
        ("localize-lidar", "-k"),
        ("localize-lidar", "--window-instances"),
        ("build-lidar-map", "--every"),
        ("bench", "raycast", "--vertices"),
        ("bench", "filter", "--stride"),
        ("bench", "triplet", "--max-kept"),
        ("build-scene-graph", "--target-vertices"),
        ("localize-camera", "--boxes"),
        ("localize-camera", "--patches"),
    ]:
        assert expected in found, expected
    commands = {path for path, _ in _leaves()}
    assert {("demo",), ("cache",), ("bench", "filter"), ("localize-camera",)} <= commands
    assert len(found) >= 45, sorted(found)


def test_every_numeric_option_has_a_checker():
    """A numeric option's values are checked by a type of jaxloc.cli._options (or are integer
    choices); a bare int or float would let 0, -3 and nan through to the library."""
    unchecked = [
        (*path, _option_name(action))
        for path, _, action in _numeric_options()
        if getattr(action.type, "__module__", None) != "jaxloc.cli._options"
        and not (action.choices is not None and all(isinstance(c, int) for c in action.choices))
    ]
    assert not unchecked, unchecked


# ----------------------------------------------------------------------------- 0, -3, nan


@pytest.mark.parametrize(("path", "dest", "value"), CASES)
def test_numeric_option_given_zero_negative_or_nan(path, dest, value, tmp_path, capsys):
    """Exit status 2 and one line naming the option, or the value is accepted: then the command
    still ends with 0 or 2 and one line, never a traceback, without running anything heavy."""
    parser, action = _lookup(path, dest)
    argv = [*path, *_needed(parser, tmp_path), action.option_strings[0], *_values(action, value)]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exit_info:
        rejected = exit_info
    else:
        rejected = None
    err = capsys.readouterr().err
    if rejected is not None:  # refused where it is parsed
        assert rejected.code == 2, (argv, err)
        line = _one_line(err)
        assert line.startswith(f"{parser.prog}: error: "), line
        assert any(name in line for name in action.option_strings), line
        assert main(["--no-cache", *argv]) == 2  # main returns the status, with the same line
        assert _one_line(capsys.readouterr().err) == line
        return
    if any(not a.option_strings for a in parser._actions):  # files to read: they do not exist
        code = main(["--no-cache", *argv])
        out, err = capsys.readouterr()
        assert code in (0, 2), (argv, out, err)
        if code == 2:
            _one_line(err)
        return
    try:  # no files: the command would run, so only its cross-option checks are called
        check_args(args)
    except InputError as error:
        assert "\n" not in str(error), error


# ----------------------------------------------------------------------------- strides and sizes


def _demo_args(*argv: str) -> argparse.Namespace:
    return build_parser().parse_args(["demo", *argv])


def test_fitting_strides_lowers_the_paper_strides_for_a_small_image():
    args = _demo_args("--width", "160", "--height", "120")
    assert args.strides is None
    strides = fitting_strides(args)
    assert strides == (18, 8, 4)
    for stride in strides:
        assert min(stride_grid_shape(stride, 160, 120)) >= SSIM_WINDOW
    assert min(stride_grid_shape(19, 160, 120)) < SSIM_WINDOW  # 18 is the largest that fits
    assert fitting_strides(_demo_args()) == SG2LocConfig.strides  # 960 x 540: the paper's
    assert fitting_strides(_demo_args("--width", "160", "--height", "120", "--strides", "8,4")) == (
        8,
        4,
    )
    check_args(args)  # the demo at 160 x 120 passes its checks with its default strides


def test_stride_grid_shape_is_the_grid_stride_grid_casts():
    from jaxloc.camera import Camera, stride_grid

    for width, height, stride in [(160, 120, 18), (160, 120, 20), (33, 17, 5), (960, 540, 20)]:
        grid = stride_grid(Camera.from_fov(width, height, 60.0), stride)
        assert tuple(grid.shape) == stride_grid_shape(stride, width, height)


def test_fitting_strides_refuses_strides_too_coarse_for_the_image(capsys):
    with pytest.raises(InputError, match=r"--strides: stride 20 gives a 6 x 8 ray grid") as info:
        fitting_strides(_demo_args("--width", "160", "--height", "120", "--strides", "20,8,4"))
    assert "at most 18" in str(info.value)
    argv = ["--no-cache", "demo", "--width", "160", "--height", "120", "--strides", "20,8,4"]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and _one_line(err).startswith("jaxloc demo: error: --strides: stride 20")


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["demo", "--width", "12"], "--width/--height: image 12x540 must hold the 9x16 patch"),
        (["demo", "--height", "8"], "want width >= 16 and height >= 9"),
        (["bench", "filter", "--stride", "20"], "--stride: stride 20 gives a 4 x 8 ray grid"),
        (["bench", "filter", "--width", "40", "--height", "30"], "use strides of at most 4"),
        (["bench", "filter", "--width", "10"], "--width/--height: image 10x90 must hold"),
        (["bench", "raycast", "--width", "8", "--stride", "40"], "--stride 40 casts no ray"),
        (["localize-lidar", "m", "s", "--accumulate", "3", "--accumulate-max", "2"], "(3), got 2"),
        (["localize-lidar", "m", "s", "--window-instances", "0"], "--window-instances is only"),
        (["localize-lidar", "m", "s", "--save-map", "x.txt"], "--save-map x.txt: the file name"),
        (
            ["localize-lidar", "m", "s", "--poses-out", "x.tum", "--pose-format", "mcap"],
            "--poses-out/--pose-format: x.tum: format 'mcap' does not fit the name",
        ),
        (
            ["localize-lidar", "m", "s", "--poses-out", "x.mcap", "--pose-format", "kitti"],
            "x.mcap: format 'kitti' does not fit the name",
        ),
        (
            ["localize-lidar", "m", "s", "--poses-out", "x.mcap", "--pose-format", "rosbag2"],
            "x.mcap: format 'rosbag2' does not fit the name",
        ),
    ],
)
def test_options_that_do_not_fit_each_other_are_one_line_before_any_work(argv, fragment, capsys):
    assert main(["--no-cache", *argv]) == 2
    out, err = capsys.readouterr()
    line = _one_line(err)
    assert out == "" and fragment in line, line
    assert line.startswith(f"jaxloc {' '.join(argv[: 2 if argv[0] == 'bench' else 1])}: error:")


# ----------------------------------------------------------------------------- list options


@pytest.mark.parametrize(
    ("command", "option", "forms", "expected"),
    [
        (["demo"], "--strides", (["10", "6", "4"], ["10,6,4"], ["10,6", "4"]), (10, 6, 4)),
        (["localize-camera", "m", "s"], "--strides", (["20", "8"], ["20,8"]), (20, 8)),
        (["localize-camera", "m", "s"], "--boxes", (["0.8", "0.4"], ["0.8,0.4"]), (0.8, 0.4)),
        (["localize-camera", "m", "s"], "--heights", (["1.2", "1.5"], ["1.2,1.5"]), (1.2, 1.5)),
        (["localize-camera", "m", "s"], "--patches", (["6", "8"], ["6,8"]), (6, 8)),
    ],
)
def test_list_options_take_spaces_or_commas(command, option, forms, expected):
    parser = build_parser()
    for form in forms:
        args = parser.parse_args([*command, option, *form])
        assert getattr(args, option[2:]) == expected, form
    assert getattr(parser.parse_args(command), option[2:]) is None  # the library's default


def test_the_demo_runs_with_strides_written_either_way(capsys):
    for form in (["10", "6", "4"], ["10,6,4"]):
        args = _demo_args("--strides", *form)
        check_args(args)
        assert fitting_strides(args) == (10, 6, 4)
    assert main(["demo", "--strides", "10", "x"]) == 2
    assert "want positive integers like 20,8,4 or 20 8 4, got 'x'" in capsys.readouterr().err
    assert main(["localize-camera", "m", "s", "--patches", "6", "8", "9"]) == 2
    err = capsys.readouterr().err
    assert _one_line(err).endswith(
        "argument --patches: want 2 values, got 3 (see " + ("jaxloc localize-camera --help)")
    )


def test_help_says_how_to_write_list_options(capsys):
    for command in (["demo"], ["localize-camera"]):
        with pytest.raises(SystemExit):
            main([*command, "--help"])
        assert "'20 8 4' or '20,8,4'" in " ".join(capsys.readouterr().out.split())


def test_the_command_line_is_thin():
    """Parse, open, run, write, print: every rule lives in the library, so ``jaxloc/cli/`` stays
    small."""
    folder = Path(__file__).resolve().parents[1] / "jaxloc" / "cli"
    lines = sum(len(path.read_text().splitlines()) for path in folder.glob("*.py"))
    assert lines <= 1500, lines
