"""Make ``hybrid-<version>.h5`` here with the psfmt of an earlier format version on the path.

    git archive 14a9371 psfmt | tar -x -C /tmp/v10     # the psfmt of format 1.0
    git archive 8f03ed0 psfmt | tar -x -C /tmp/v11     # the psfmt of format 1.1 (the last before 1.2)
    PYTHONPATH=/tmp/v10:tests python tests/psfmt/data/make_old_versions.py
    PYTHONPATH=/tmp/v11:tests python tests/psfmt/data/make_old_versions.py

The files are kept, not remade by the tests: they are what those versions wrote.
"""

from __future__ import annotations

from helpers.format_versions import old_capture, old_file

import psfmt

if __name__ == "__main__":
    version = psfmt.FORMAT_VERSION_STR
    print(psfmt.write(old_capture(version), old_file(version)))
