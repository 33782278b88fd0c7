"""The job side shared by the API and the workers: settings, DB models, object store.

Nothing here imports geometry at import time (the API imports this package); functions
that need the pipeline (sequence summaries, mesh checks) import it inside their body.
"""
