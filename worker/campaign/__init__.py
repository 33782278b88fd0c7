"""Dataset campaigns: many obstacles in many sequences from one spec.

- :mod:`worker.campaign.spec`: the campaign spec (pydantic; YAML or JSON files).
- :mod:`worker.campaign.variant`: what a spec expands into (variants with resolved positions).
- :mod:`worker.campaign.placement`: where an object may stand in a prepared sequence (zones,
  footprints, poles, platforms, the track bed, spacing).
- :mod:`worker.campaign.expand`: the deterministic expansion and the validation.
- :mod:`worker.campaign.run`: a campaign run embedded (``osdar-ar campaign run``): one
  preparation per sequence, each variant as an augmentation job, resuming.
- :mod:`worker.campaign.manifest`: manifest.json and manifest.csv, one row per variant.
- :mod:`worker.campaign.contact_sheet`: one frame per variant in a labelled grid (PNG).

This ``__init__`` imports nothing, so that the spec module stays light (pydantic only).
"""
