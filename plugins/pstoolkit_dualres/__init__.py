"""First-party plugin: the `dualres` DualResPS solver (frames + events, neural inverse rendering)."""
