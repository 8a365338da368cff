"""The typer application and the entry point that turns user errors into one line and exit code 2."""

from __future__ import annotations

import sys

import click
import typer

from psfmt import FormatError
from pstoolkit.errors import UserError

app = typer.Typer(
    name="pstoolkit",
    help="Photometric stereo from frames, events or both: run solvers, simulate, convert and inspect captures.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def fail(message: str) -> None:
    """Print one error line to stderr."""
    typer.echo(f"pstoolkit: error: {message}", err=True)


def main(argv: list[str] | None = None) -> int:
    """Console entry point. Exit codes: 0 success, 1 a negative finding (validate), 2 a user error."""
    try:
        code = app(args=argv, prog_name="pstoolkit", standalone_mode=False)
    except click.exceptions.Exit as exc:
        code = exc.exit_code
    except click.ClickException as exc:
        exc.show()
        code = exc.exit_code
    except click.exceptions.Abort:
        fail("interrupted")
        code = 130
    except KeyboardInterrupt:
        fail("interrupted")
        code = 130
    except (UserError, FormatError) as exc:
        fail(str(exc))
        code = 2
    except OSError as exc:
        fail(f"{exc.filename or ''}: {exc.strerror or exc}".lstrip(": "))
        code = 2
    code = int(code or 0)
    if argv is None:
        sys.exit(code)
    return code
