"""Orchestration: the Celery app and its thin tasks, the job runner, queue, reaper, job
state and the embedded mode. The pipeline's steps live beside it in ``worker``; the
platform it shares with the API (settings, database, store) in ``osdar_platform``.
"""
