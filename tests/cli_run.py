"""Running a trundle command in the test's own process, its output taken from pytest's capsys."""

from __future__ import annotations

import pytest

from trundle.tools.cli.main import main


def trundle(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    """Run ``trundle ARGV``: (exit code, stdout, stderr), the output of this command alone."""
    capsys.readouterr()
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def succeeds(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[str, str]:
    """Run ``trundle ARGV``, which must end with exit code 0 and no traceback: (stdout, stderr)."""
    code, out, err = trundle(capsys, *argv)
    assert code == 0 and "Traceback" not in err, (argv, code, err)
    return out, err
