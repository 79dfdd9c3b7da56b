"""The CLI's usage errors (argparse: an unknown argument, a bad choice, a missing one) are
one ``error:`` line naming the command and its --help, exit code 2, as every other bad input;
--help itself still prints the usage and exits 0."""

from __future__ import annotations

import pytest

from macromicro_sumo.cli import main


@pytest.mark.parametrize(
    ("argv", "fragments"),
    [
        (["doctor", "extra"], ("macromicro", "unrecognized arguments: extra")),
        (["export", "x", "--format", "xml"], ("macromicro export", "'xml'", "csv", "parquet")),
        (["simulate"], ("macromicro simulate", "--out")),
        (["deploy", "s.toml", "--out", "o"], ("macromicro deploy", "--policy")),
        (["nosuch"], ("macromicro", "'nosuch'", "simulate")),
        ([], ("macromicro", "command")),
    ],
)
def test_usage_errors_are_one_line(
    argv: list[str], fragments: tuple[str, ...], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and err.startswith("error: "), err
    assert "--help" in err and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in err, (fragment, err)


def test_help_still_prints_usage(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["run", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: macromicro run") and "deployment" in out
