"""First-party plugin: event-file converters (Prophesee RAW EVT 3.0/2.0, DSEC-style HDF5)."""
