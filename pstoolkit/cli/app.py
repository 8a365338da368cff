"""The typer application, the progress bar every command draws, and the entry point that turns user
errors into one line and exit code 2."""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

import typer

from psfmt import FormatError
from psfmt.isolate import isolated
from psfmt.text import printable
from pstoolkit._shared.allocator import keep_freed_memory
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.cli.help import PlainCommand, PlainGroup
from pstoolkit.errors import Interrupted, UserError
from pstoolkit.version import __version__


class _Typer(typer.Typer):
    """A Typer whose commands print their help with plain metavars (``pstoolkit.cli.help``): every
    ``@app.command()``, the plugins' too, gets ``PlainCommand`` unless it names its own class."""

    def command(self, *args: Any, **kwargs: Any) -> Callable[[Any], Any]:
        kwargs.setdefault("cls", PlainCommand)
        return super().command(*args, **kwargs)


app = _Typer(
    name="pstoolkit",
    cls=PlainGroup,
    help="Photometric stereo from frames, events or both: run solvers, simulate, convert and inspect captures.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(shown: bool) -> None:
    """``--version``: print ``pstoolkit VERSION`` and stop (eager: before any command is looked at)."""
    if shown:
        echo(f"pstoolkit {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", is_eager=True, callback=_version, help="Print the version and exit."
    ),
) -> None:
    # the group's own options, which act in their callbacks; the group's help is Typer(help=...)'s
    del version


QUIET_HELP = "No progress bar and no notes on stderr (errors are still printed)."
"""The help of ``-q/--quiet``, which every command takes (some also drop their summary line)."""

_open_bars: list[ProgressBar] = []


def _stderr_console() -> Any:
    """The rich console of the progress bars: stderr (a function, so tests can hand in a fake terminal)."""
    from rich.console import Console  # deferred: rich is only needed once a bar is shown

    return Console(stderr=True)


class ProgressBar:
    """``progress(fraction, message)`` (``pstoolkit._shared.progress.Progress``) drawn with rich: the label, a
    bar, the percentage, the time remaining and the whole message. The bar starts on the first call,
    ends on a line of its own when the fraction reaches 1, and starts again if a later call goes back
    below 1 (a second phase)."""

    def __init__(self, label: str, console: Any) -> None:
        self.label = printable(label)
        self.console = console
        self._progress: Any = None
        self._task: Any = None
        self._done = False
        self._percent = -1

    def __call__(self, fraction: float, message: str) -> None:
        fraction = min(max(float(fraction), 0.0), 1.0) if fraction == fraction else 0.0  # NaN: nothing done yet
        if fraction >= 1.0 and self._done:  # the end reported again: the bar has ended already
            return
        if self._progress is None:
            self._start()
        self._done = False
        percent = int(100 * fraction)
        # drawn at once when the whole percent changes; between those rich redraws ten times a second
        self._progress.update(self._task, completed=fraction, message=printable(message), refresh=percent != self._percent)
        self._percent = percent
        if fraction >= 1.0:
            self.close()
            self._done = True

    def _start(self) -> None:
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn
        from rich.table import Column

        # markup off: labels and messages carry file names and brackets, not rich markup. The message
        # takes the rest of the line (expand, ratio 1) and only a terminal too narrow for it cuts it,
        # with an ellipsis: the label, bar, percentage and time remaining keep their width. stdout and
        # stderr are not redirected: rich would move what a command prints on stdout to stderr.
        self._progress = Progress(
            TextColumn("{task.description}", markup=False, table_column=Column(no_wrap=True)),
            BarColumn(bar_width=20),
            TaskProgressColumn(),
            TimeRemainingColumn(),
            TextColumn("{task.fields[message]}", markup=False, table_column=Column(no_wrap=True, overflow="ellipsis", ratio=1)),
            console=self.console,
            expand=True,
            redirect_stdout=False,
            redirect_stderr=False,
        )
        self._progress.start()
        self._task = self._progress.add_task(self.label, total=1.0, message="")
        _open_bars.append(self)

    def close(self) -> None:
        """End the bar where it stands (its last state stays on screen); nothing if it is not shown."""
        if self._progress is not None:
            self._progress.stop()
            self._progress = None
            _open_bars.remove(self)


def close_progress() -> None:
    """End every bar still shown, so that the next line printed starts on a line of its own."""
    for bar in list(_open_bars):
        bar.close()


def progress_bar(label: str, quiet: bool = False, *, console: Any = None) -> Progress:
    """A progress bar on stderr (``ProgressBar``); nothing when ``quiet`` or when stderr is not a
    terminal (pipes, CI, files). ``console``: the rich console to draw on (default: stderr)."""
    if quiet:
        return no_progress
    console = _stderr_console() if console is None else console
    return ProgressBar(label, console) if console.is_terminal else no_progress


def echo(text: str, *, err: bool = False, nl: bool = True) -> None:
    """Print ``text`` (lines) to stdout or stderr without the control characters a string from a file
    may carry (``psfmt.text.printable``): every command prints through here. A bar still shown ends
    first, so the text is not drawn over."""
    close_progress()
    typer.echo(printable(text, newlines=True), err=err, nl=nl)


def fail(message: str) -> None:
    """Print one error line to stderr (one line whatever the message holds)."""
    close_progress()
    typer.echo(f"pstoolkit: error: {printable(message)}", err=True)


def _usage_error(exc: BaseException) -> bool:
    """Click's usage errors, whether typer uses click or its own vendored copy of it."""
    return hasattr(exc, "format_message") and isinstance(getattr(exc, "exit_code", None), int)


_terminated = threading.Event()


# Seconds before a SIGTERM that arrived inside numba's compiler is delivered again.
RESEND_S = 0.1


def _in_compiler(frame: FrameType | None) -> bool:
    """Whether ``frame`` or a caller runs in llvmlite, whose callbacks from C (numba compiling a
    kernel) print and drop any exception raised in them."""
    while frame is not None:
        if str(frame.f_globals.get("__name__", "")).startswith("llvmlite"):
            return True
        frame = frame.f_back
    return False


def _terminate(signum: int, frame: FrameType | None) -> None:
    """SIGTERM: raised in the main thread as a Ctrl-C is, so that the same clean-up runs (a temporary
    file removed, a partial folder deleted); the command then exits with 143. Inside numba's compiler
    the exception would be printed and lost, so the signal is sent again a moment later instead."""
    _terminated.set()
    if _in_compiler(frame):
        resend = threading.Timer(RESEND_S, os.kill, (os.getpid(), signal.SIGTERM))
        resend.daemon = True
        resend.start()
        return
    raise KeyboardInterrupt


def _interrupted() -> int:
    """Print why the command stopped; the exit code: 143 for SIGTERM, 130 for Ctrl-C."""
    if _terminated.is_set():
        fail("terminated")
        return 143
    fail("interrupted")
    return 130


def main(argv: list[str] | None = None) -> int:
    """Console entry point. Exit codes: 0 success, 1 a negative finding (validate), 2 a user error
    (a usage error, a bad file, a bad option), 130 interrupted, 143 terminated (SIGTERM, which cleans
    up as Ctrl-C does). Every error is one line on stderr. Captures are checked in a child process
    before they are read (``psfmt.isolate``), so a file that would hang or crash HDF5 is one more bad
    file."""
    keep_freed_memory()
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    _terminated.clear()
    try:
        with isolated():
            result = app(args=argv, prog_name="pstoolkit", standalone_mode=False)
        code = result if isinstance(result, int) else 0
        if code == 130:  # typer turns Ctrl-C inside a command into Exit(130) without a word
            code = _interrupted()
    except KeyboardInterrupt:
        code = _interrupted()
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
            code = _interrupted()
        elif _usage_error(exc):
            fail(exc.format_message())  # type: ignore[attr-defined]
            code = exc.exit_code  # type: ignore[attr-defined]
        else:
            raise
    finally:
        close_progress()
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    if argv is None:
        sys.exit(code)
    return code
