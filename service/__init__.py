"""The job service's HTTP API (FastAPI): ``service.app:create_app``.

Imports no geometry: the pipeline is reached through ``worker.jobs`` (settings, tables,
store, queue) and, at request time only, ``worker.orchestration.inspect``.
"""
