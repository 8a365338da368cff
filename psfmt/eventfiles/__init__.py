"""Foreign event files, read into and written from psfmt's event arrays: Prophesee RAW (``evt3``,
``evt2``, their header ``rawheader`` and the sensors it implies ``rawsensors``), Metavision DAT
(``dat``) and HDF5 (``metavision_hdf5``, with the ECF decoder in ``_ecf``), DSEC-style HDF5
(``dsec``) and tonic's structured arrays (``structured``). See ``docs/event-files.md``."""
