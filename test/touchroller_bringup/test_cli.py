"""The `touchroller` command's contract: subcommands listed, bad input is one line and a non-zero exit."""
from __future__ import annotations

import subprocess
import sys

import pytest

from touchroller_bringup import cli
from touchroller_bringup.errors import UserError


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        assert name in out


def test_unknown_subcommand_and_missing_arguments_are_one_line(capsys):
    for argv in (["frobnicate"], []):
        with pytest.raises(SystemExit) as info:
            cli.main(argv)
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("touchroller")


def test_a_command_line_naming_a_subcommand_builds_only_its_parser(capsys):
    """`touchroller map ...` imports none of the other commands' modules (start-up time); its own help and
    errors are as with the whole parser."""
    only = cli.build_parser(only="map")
    (action,) = only._subparsers._group_actions
    assert list(action.choices) == ["map"]
    with pytest.raises(SystemExit) as info:
        cli.main(["map", "--help"])
    assert info.value.code == 0 and "usage: touchroller map" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        cli.main(["map"])
    assert info.value.code == 2 and "the following arguments are required" in capsys.readouterr().err


def test_user_errors_and_unexpected_errors_never_show_a_traceback(monkeypatch, capsys):
    def boom(_args):
        raise UserError("the bag is empty")

    def crash(_args):
        raise RuntimeError("something deep")

    for func, code, text in ((boom, 2, "the bag is empty"), (crash, 1, "RuntimeError: something deep")):
        parser = cli.build_parser()
        monkeypatch.setattr(cli, "build_parser", lambda only=None, parser=parser, func=func: _with_func(parser, func))
        assert cli.main(["bench", "--list"]) == code
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and text in err and "Traceback" not in err


def _with_func(parser, func):
    parser.set_defaults(func=func)
    for action in parser._subparsers._group_actions:
        for sub in action.choices.values():
            sub.set_defaults(func=func)
    return parser


def test_console_script_runs_as_a_process():
    result = subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "bench", "--list"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "geometry_stability" in result.stdout


def test_a_reader_that_closes_the_pipe_early_is_not_an_error():
    # as `touchroller bench --list | head -1`: the reader takes one line and goes away
    process = subprocess.Popen([sys.executable, "-m", "touchroller_bringup.cli", "bench", "--list"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
    process.stdout.close()          # nobody reads: the first write breaks the pipe
    err = process.stderr.read().decode()
    assert process.wait(timeout=60) == 141 and err == ""


def test_ctrl_c_while_the_parser_is_built_is_one_line_not_a_traceback(monkeypatch, capsys):
    """#28: a SIGINT in the first 0.1-0.3 s (the parser and the command's imports) printed a traceback."""
    def interrupted(only=None):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["contacts", "x", "--out", "y"]) == 130
    assert capsys.readouterr().err.strip() == "touchroller: error: interrupted"


@pytest.mark.parametrize("error, words", [
    (OSError(28, "No space left on device", "/x/out.csv"), ("/x/out.csv", "disk is full")),
    (OSError(30, "Read-only file system", "/ro/out.csv"), ("/ro/out.csv", "write elsewhere")),
    (IsADirectoryError(21, "Is a directory", "/x/dir"), ("/x/dir", "give a file name")),
])
def test_an_os_error_is_one_sentence_naming_the_file_and_what_to_do(monkeypatch, capsys, error, words):
    def fail(args):
        raise error
    monkeypatch.setattr("touchroller_bringup.commands.reindex.run", fail)
    assert cli.main(["reindex", "bag"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "OSError" not in err and all(w in err for w in words), err


def test_a_sqlite_error_is_one_sentence(monkeypatch, capsys):
    import sqlite3

    def fail(args):
        raise sqlite3.OperationalError("database or disk is full")
    monkeypatch.setattr("touchroller_bringup.commands.reindex.run", fail)
    assert cli.main(["reindex", "bag"]) == 1
    err = capsys.readouterr().err.strip()
    assert "OperationalError" not in err and "free some space" in err, err


def test_only_the_console_script_leaves_its_objects_out_of_the_last_garbage_collection(monkeypatch, capsys):
    """`main()` as the console script calls it (no arguments: the process exits next) freezes what is alive,
    so the interpreter's collection at exit does not walk it; a caller passing its arguments goes on
    running and keeps its garbage collector as it was."""
    import gc

    assert gc.get_freeze_count() == 0
    try:
        assert cli.main(["bench", "--list"]) == 0
        assert gc.get_freeze_count() == 0
        monkeypatch.setattr(sys, "argv", ["touchroller", "bench", "--list"])
        assert cli.main() == 0
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
    assert "geometry_stability" in capsys.readouterr().out
