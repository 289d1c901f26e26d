"""The staged DAG engine: artifact keys, on-disk store, locks, executors, CLI.

It knows nothing of bodies, cameras or recipes' contents: a domain package hands it a
:class:`pipeline.spec.Registry` (``python -m pipeline ... --registry stages``). Modules:
``spec`` (the contract), ``hashing`` (keys), ``store`` (artifact folders, locks),
``plan`` (DAG closure and keys), ``executors`` (serial; the Dask seam), ``engine`` (run,
status), ``cli``.
"""
