"""Revisions of the job store's schema, oldest first (``NNNN_<what>.py``)."""
