"""Scoring normal maps (``scoring``), the metrics (``metrics``), tables of scored results and the
evaluation report (``report``, ``markup``)."""
