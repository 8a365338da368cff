"""First-party plugin: event-file converters (Prophesee RAW EVT 3.0/2.0, Metavision DAT and HDF5, DSEC-style
HDF5, iniVation AEDAT4).

The import sits inside the hook, so the command line starts without loading this plugin's modules.
"""

from __future__ import annotations

from pstoolkit import Registry, hookimpl


@hookimpl
def pstoolkit_register_converters(registry: Registry) -> None:
    from pstoolkit_eventfiles.aedat4 import Aedat4
    from pstoolkit_eventfiles.converters import Dat, Dsec, Hdf5, Raw

    for converter in (Raw, Dat, Hdf5, Dsec, Aedat4):
        registry.register(converter)
