"""Files in and out: reading mesh files (``meshfile.py``; STL itself in ``stl.py`` and ``stl_ascii.py``, the
readers' shared ``RawMesh`` in ``rawmesh.py``), writing files atomically (``atomic.py``), JSON reports
(``report.py``)."""
