"""aeromag: post-flight processing of airborne and UAV magnetic surveys.

The library is pure: functions and small estimator objects on numpy/pandas data.
File access lives in :mod:`pipeline.io`; Prefect lives in ``flows/`` only.
"""

__version__ = "0.1.0"
