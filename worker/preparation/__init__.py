"""Sequence preparation (pipeline step 2): poses, registered cloud, tracks, scene elements.

The step itself is :func:`worker.preparation.prepare.prepare`; the modules beside it are
its parts (registration, rails, centrelines, localization strategies, scene elements, the
calibration point, the cached artifact).
"""
