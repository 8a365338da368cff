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
