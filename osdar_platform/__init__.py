"""The platform shared by the API (``service``) and the workers: settings, database and
models, migrations glue, API keys, object store, archive safety and the catalogue of names
a job spec may use. It imports no geometry and nothing of ``service`` or ``worker``.
"""
