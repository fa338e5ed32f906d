"""The CLI's error contract, checked the same way everywhere: exit code 1, exactly one line on
stderr that starts with ``error:`` and names the problem, no traceback."""

from __future__ import annotations


def assert_one_error_line(result, *needles: str) -> str:
    """Assert the contract on a ``CliRunner`` result; returns the error line."""
    assert result.exit_code == 1, result.output
    assert isinstance(result.exception, SystemExit), repr(result.exception)  # not an uncaught exception
    assert "Traceback" not in result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error:"), lines[0]
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]
