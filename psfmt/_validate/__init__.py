"""The checks behind ``psfmt.validate``, one module per job: the findings they collect, the value
checks every group shares, storage, one module per group of the file (frames, events and triggers,
lights, calibration, ground-truth and result maps), the bounded block reader, and the two tiers that
run them (``structure``, then ``content``)."""
