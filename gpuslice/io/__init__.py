"""Files in and out: reading mesh files (``meshfile.py``), writing files atomically (``atomic.py``), JSON reports
(``report.py``)."""
