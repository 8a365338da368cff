"""The EVT 3.0 kernels behind ``psfmt.eventfiles.evt3``: the word layout, the engine choice, and the decoder's
and encoder's loops, each as a compiled loop and as whole-array numpy, on plain arrays and a state
array that carries over from block to block."""
