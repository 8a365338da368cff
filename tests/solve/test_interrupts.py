"""Issue 19, item 14: Ctrl-C while the command's modules import (torch, numba, matplotlib: seconds)
ends in one line and exit code 130, like a Ctrl-C anywhere later."""

from __future__ import annotations

import subprocess
import sys
import textwrap

# The pstoolkit console script, with a Ctrl-C arriving exactly while torch is being imported.
INTERRUPTED_IMPORT = textwrap.dedent(
    """
    import sys


    class CtrlC:
        def find_spec(self, name, path=None, target=None):
            if name == "torch":
                raise KeyboardInterrupt
            return None


    sys.meta_path.insert(0, CtrlC())
    from pstoolkit.cli import main

    sys.exit(main())
    """
)


def test_ctrl_c_while_the_commands_import_is_one_line() -> None:
    done = subprocess.run([sys.executable, "-c", INTERRUPTED_IMPORT, "plugins"], capture_output=True, text=True, timeout=300)
    assert (done.returncode, done.stdout, done.stderr) == (130, "", "pstoolkit: error: interrupted\n")


# A loop callback error logged after distributed has been imported inside the block, as the batch and
# tile commands do (connect imports it): distributed's cancel callback logs a NameError traceback
# there when a Ctrl-C lands before its future exists.
LOOP_ERROR = textwrap.dedent(
    """
    import logging
    import sys
    from contextlib import nullcontext

    from pstoolkit.solve.cluster import quiet_loop_errors

    with quiet_loop_errors() if sys.argv[1] == "quiet" else nullcontext():
        import distributed

        logging.getLogger("tornado.application").error("Exception in callback cancel")
    """
)


def test_the_loops_callback_errors_stay_silent_when_distributed_is_imported_in_the_block() -> None:
    runs = {how: subprocess.run([sys.executable, "-c", LOOP_ERROR, how], capture_output=True, text=True, timeout=300) for how in ("quiet", "plain")}
    assert (runs["quiet"].returncode, runs["quiet"].stderr) == (0, "")
    assert "Exception in callback cancel" in runs["plain"].stderr  # distributed's handler prints it otherwise
