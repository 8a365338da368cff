"""The ECF kernels behind ``psfmt.eventfiles.metavision_hdf5``: the chunk format (``chunk``), its decoder as a
compiled loop (``loop``) and as whole-array numpy (``vector``), both giving the same events and the
same error codes for the same chunk bytes."""
