"""The typer application and the entry point that turns user errors into one line and exit code 2."""

from __future__ import annotations

import sys

import typer

from psfmt import FormatError
from psfmt.isolate import isolated
from psfmt.text import printable
from pstoolkit._shared.allocator import keep_freed_memory
from pstoolkit.errors import Interrupted, UserError
from pstoolkit.solve.base import Progress, no_progress

app = typer.Typer(
    name="pstoolkit",
    help="Photometric stereo from frames, events or both: run solvers, simulate, convert and inspect captures.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def terminal_progress(label: str) -> Progress:
    """A one-line percentage on stderr, redrawn only when the whole percent changes."""
    shown = [-1]

    def report(fraction: float, message: str) -> None:
        percent = int(100 * min(max(fraction, 0.0), 1.0))
        if percent != shown[0]:
            shown[0] = percent
            end = "\n" if percent == 100 else ""
            sys.stderr.write(f"\r{label}: {percent:3d} % {message:<20.20}{end}")
            sys.stderr.flush()

    return report


def progress_bar(label: str, quiet: bool = False) -> Progress:
    """Progress on a terminal; nothing when ``quiet`` or when stderr is not a terminal (pipes, CI)."""
    return no_progress if quiet or not sys.stderr.isatty() else terminal_progress(label)


def echo(text: str, *, err: bool = False, nl: bool = True) -> None:
    """Print ``text`` (lines) to stdout or stderr without the control characters a string from a file
    may carry (``psfmt.text.printable``): every command prints through here."""
    typer.echo(printable(text, newlines=True), err=err, nl=nl)


def fail(message: str) -> None:
    """Print one error line to stderr (one line whatever the message holds)."""
    typer.echo(f"pstoolkit: error: {printable(message)}", err=True)


def _usage_error(exc: BaseException) -> bool:
    """Click's usage errors, whether typer uses click or its own vendored copy of it."""
    return hasattr(exc, "format_message") and isinstance(getattr(exc, "exit_code", None), int)


def main(argv: list[str] | None = None) -> int:
    """Console entry point. Exit codes: 0 success, 1 a negative finding (validate), 2 a user error
    (a usage error, a bad file, a bad option), 130 interrupted. Every error is one line on stderr.
    Captures are checked in a child process before they are read (``psfmt.isolate``), so a file that
    would hang or crash HDF5 is one more bad file."""
    keep_freed_memory()
    try:
        with isolated():
            result = app(args=argv, prog_name="pstoolkit", standalone_mode=False)
        code = result if isinstance(result, int) else 0
        if code == 130:  # typer turns Ctrl-C inside a command into Exit(130) without a word
            fail("interrupted")
    except KeyboardInterrupt:
        fail("interrupted")
        code = 130
    except Interrupted as exc:
        fail(f"interrupted: {exc}")
        code = 130
    except (UserError, FormatError) as exc:
        fail(str(exc))
        code = 2
    except OSError as exc:
        fail(f"{exc.filename or ''}: {exc.strerror or exc}".lstrip(": "))
        code = 2
    except MemoryError as exc:
        # limits keep files from asking for this; a solver on a capture too large for this machine can
        fail(f"out of memory ({str(exc) or 'an allocation failed'}); try a smaller capture or a machine with more memory")
        code = 2
    except Exception as exc:
        if type(exc).__name__ == "Abort":  # click turns Ctrl-C inside a command into Abort
            fail("interrupted")
            code = 130
        elif _usage_error(exc):
            fail(exc.format_message())  # type: ignore[attr-defined]
            code = exc.exit_code  # type: ignore[attr-defined]
        else:
            raise
    if argv is None:
        sys.exit(code)
    return code
