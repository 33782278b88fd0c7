"""The job service's HTTP API (FastAPI): ``service.app:create_app``.

Imports no geometry: the platform (``osdar_platform``: settings, tables, store) and
the queue (``worker.orchestration.queue``) are what it uses; the pipeline is reached at
request time only, through ``worker.orchestration.inspect``.
"""
